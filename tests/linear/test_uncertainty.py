"""Covariance estimators, checked against statsmodels on the full design with level dummies."""

from __future__ import annotations

import functools
import tracemalloc
from dataclasses import dataclass

import numpy as np
import pytest
import statsmodels.api as sm
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal, stats

from hamid.errors import FitError
from hamid.linear.uncertainty import (
    DESCRIPTIONS,
    ESTIMATORS,
    Covariance,
    ScoreSums,
    bartlett_bandwidth,
    bootstrap,
    confidence_bounds,
    covariance,
)

SIZES = (90, 130, 180)
THETA = np.array([1.0, -2.0, 0.5])
CLUSTER_ROWS = 25


@dataclass(frozen=True)
class Data:
    A: np.ndarray
    b: np.ndarray
    w: np.ndarray
    groups: np.ndarray
    h: np.ndarray


@dataclass(frozen=True)
class Fit:
    theta: np.ndarray
    h: np.ndarray
    r: np.ndarray
    G: np.ndarray
    lam: np.ndarray
    Abar: np.ndarray
    df_resid: int


def _ar1(rng, shape, rho):
    """Stationary AR(1) series along axis 0 with unit variance."""
    e = rng.standard_normal(shape)
    e[0] /= np.sqrt(1 - rho**2)
    return signal.lfilter([1.0], [1.0, -rho], e, axis=0) * np.sqrt(1 - rho**2)


def _simulate(seed, sizes=SIZES, *, rho=0.6, rho_x=0.8, weighted=False, hetero=True, p=3):
    """Rows b = A theta + h_g + e, AR(1) regressors and errors within each trajectory."""
    rng = np.random.default_rng(seed)
    groups = np.repeat(np.arange(len(sizes)), sizes)
    A = np.concatenate([_ar1(rng, (m, p), rho_x) for m in sizes]) + rng.normal(size=p)
    e = np.concatenate([_ar1(rng, m, rho) for m in sizes])
    if hetero:
        e *= 0.5 + np.abs(A[:, 0])
    w = rng.uniform(0.5, 2.0, len(groups)) if weighted else np.ones(len(groups))
    h = rng.normal(scale=3.0, size=len(sizes))
    b = A @ THETA[:p] + h[groups] + e / np.sqrt(w)
    return Data(A, b, w, groups, h)


def _fit(A, b, w, groups):
    """Weighted centring within trajectories, then lstsq; G from the pseudo-inverse."""
    n_groups = int(groups.max()) + 1
    W = np.bincount(groups, weights=w, minlength=n_groups)
    Abar = np.stack([np.bincount(groups, weights=w * a, minlength=n_groups) for a in A.T], 1)
    Abar /= W[:, None]
    bbar = np.bincount(groups, weights=w * b, minlength=n_groups) / W
    At = A - Abar[groups]
    sw = np.sqrt(w)
    theta = np.linalg.lstsq(sw[:, None] * At, sw * (b - bbar[groups]), rcond=None)[0]
    h = np.bincount(groups, weights=w * (b - A @ theta), minlength=n_groups) / W
    r = b - A @ theta - h[groups]
    # pinv(sqrt(W) At) = (At' W At)^-1 At' sqrt(W), so G_i = sqrt(w_i) pinv[:, i]
    G = (np.linalg.pinv(sw[:, None] * At) * sw).T
    lam = w / W[groups]
    return Fit(theta, h, r, G, lam, Abar, len(b) - A.shape[1] - n_groups)


def _clusters(groups):
    """Blocks of CLUSTER_ROWS consecutive rows within each trajectory, numbered globally."""
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    local = np.arange(len(groups)) - np.repeat(starts, np.diff(np.r_[starts, len(groups)]))
    key = groups * len(groups) + local // CLUSTER_ROWS
    return np.unique(key, return_inverse=True)[1]


def _full_cov(cov: Covariance, Abar):
    """Covariance of [theta, h] from the blocks: h_j - h = m_j - Abar_j (theta_hat - theta)."""
    p, n_groups = cov.theta.shape[0], len(cov.level)
    V = np.empty((p + n_groups, p + n_groups))
    V[:p, :p] = cov.theta
    V[p:, :p] = cov.theta_level - Abar @ cov.theta
    V[:p, p:] = V[p:, :p].T
    cross = Abar @ cov.theta_level.T
    V[p:, p:] = np.diag(cov.level) - cross - cross.T + Abar @ cov.theta @ Abar.T
    return V


def _h_variance(cov: Covariance, Abar):
    """Var(h_j) as the lead computes it."""
    return (
        cov.level
        - 2 * np.einsum("jk,jk->j", Abar, cov.theta_level)
        + np.einsum("jk,kl,jl->j", Abar, cov.theta, Abar)
    )


def _statsmodels(data: Data, cov_type, cov_kwds):
    n_groups = int(data.groups.max()) + 1
    dummies = (data.groups[:, None] == np.arange(n_groups)).astype(float)
    X = np.column_stack((data.A, dummies))
    return sm.WLS(data.b, X, weights=data.w).fit(cov_type=cov_type, cov_kwds=cov_kwds, use_t=True)


def _cov(kind, data: Data, fit: Fit, **options):
    return covariance(
        kind, fit.G, fit.lam, fit.r, data.w, data.groups, df_resid=fit.df_resid, **options
    )


# kind, trajectory sizes, bandwidth ("auto": chosen by the plug-in), statsmodels cov_type
CASES = [
    ("classical", SIZES, None, "nonrobust"),
    ("hc", SIZES, None, "HC1"),
    ("hac", (400,), 5, "HAC"),
    ("hac", (400,), "auto", "HAC"),
    ("hac", SIZES, 5, "hac-panel"),
    ("hac", SIZES, "auto", "hac-panel"),
]


@pytest.mark.parametrize("weighted", [False, True], ids=["unweighted", "weighted"])
@pytest.mark.parametrize(("kind", "sizes", "bandwidth", "cov_type"), CASES)
def test_matches_statsmodels_on_full_design(kind, sizes, bandwidth, cov_type, weighted):
    data = _simulate(1, sizes, weighted=weighted)
    fit = _fit(data.A, data.b, data.w, data.groups)
    options = {}
    if kind == "hac":
        lags = bandwidth
        if bandwidth == "auto":
            lags = bartlett_bandwidth(fit.G, fit.lam, fit.r, data.groups)
            assert lags >= 2  # autocorrelated scores: the plug-in must not fall back to HC
        else:
            options["bandwidth"] = lags
    cov = _cov(kind, data, fit, **options)

    kwds = {}
    if cov_type == "HAC":
        kwds = {"maxlags": lags, "use_correction": True}
    elif cov_type == "hac-panel":
        kwds = {
            "groups": data.groups,
            "maxlags": lags,
            "use_correction": "hac",
            "df_correction": False,
        }
    res = _statsmodels(data, cov_type, kwds)
    p = len(fit.theta)

    np.testing.assert_allclose(np.r_[fit.theta, fit.h], res.params, rtol=1e-9)
    expected = res.cov_params()
    np.testing.assert_allclose(cov.theta, expected[:p, :p], rtol=1e-6)
    np.testing.assert_allclose(np.sqrt(_h_variance(cov, fit.Abar)), res.bse[p:], rtol=1e-6)
    scale = np.abs(expected).max()
    np.testing.assert_allclose(_full_cov(cov, fit.Abar), expected, rtol=1e-6, atol=1e-9 * scale)

    df = getattr(res, "df_resid_inference", None) or res.df_resid
    assert cov.df == df
    se = np.sqrt(np.diag(_full_cov(cov, fit.Abar)))
    low, high = confidence_bounds(np.r_[fit.theta, fit.h], se, cov.df, 0.95)
    np.testing.assert_allclose(np.column_stack((low, high)), res.conf_int(0.05), rtol=1e-6)
    assert cov.kind == kind
    if kind == "hac":
        assert f"bandwidth {lags}" in cov.description


def test_descriptions_cover_every_estimator():
    assert set(ESTIMATORS) | {"bootstrap"} == set(DESCRIPTIONS)


@functools.cache
def _reference():
    data = _simulate(2, weighted=True)
    return data, _fit(data.A, data.b, data.w, data.groups)


@settings(max_examples=20, deadline=None)
@given(
    kind=st.sampled_from(sorted(ESTIMATORS)),
    scale=st.lists(st.floats(1e-3, 1e3), min_size=3, max_size=3),
)
def test_parameter_units_rescale_covariance_only(kind, scale):
    """A parameter in other units rescales its rows of G; the bandwidth must not move."""
    data, fit = _reference()
    d = np.array(scale)
    base = _cov(kind, data, fit)
    scaled = covariance(
        kind,
        fit.G * d,
        fit.lam,
        fit.r,
        data.w,
        data.groups,
        df_resid=fit.df_resid,
    )
    np.testing.assert_allclose(scaled.theta, base.theta * np.outer(d, d), rtol=1e-9)
    # classical cross terms are zero up to rounding: compare on the Cauchy-Schwarz scale
    bound = np.sqrt(np.outer(scaled.level, np.diag(scaled.theta))).max()
    np.testing.assert_allclose(
        scaled.theta_level, base.theta_level * d, rtol=1e-9, atol=1e-12 * bound
    )
    np.testing.assert_allclose(scaled.level, base.level, rtol=1e-12)
    assert scaled.description == base.description


@settings(max_examples=12, deadline=None)
@given(kind=st.sampled_from(sorted(ESTIMATORS)), order=st.permutations(range(len(SIZES))))
def test_trajectory_order_only_relabels_levels(kind, order):
    """Stacking the trajectories in another order permutes the level blocks, nothing else."""
    data, fit = _reference()
    rows = np.concatenate([np.flatnonzero(data.groups == j) for j in order])
    relabel = np.argsort(order)  # old label -> new label
    groups = relabel[data.groups[rows]]
    base = _cov(kind, data, fit)
    moved = covariance(
        kind,
        fit.G[rows],
        fit.lam[rows],
        fit.r[rows],
        data.w[rows],
        groups,
        df_resid=fit.df_resid,
    )
    np.testing.assert_allclose(moved.theta, base.theta, rtol=1e-9)
    # classical cross terms are zero up to rounding: compare on the Cauchy-Schwarz scale
    bound = np.sqrt(np.outer(base.level, np.diag(base.theta))).max()
    np.testing.assert_allclose(moved.theta_level, base.theta_level[list(order)], rtol=1e-9,
                               atol=1e-12 * bound)
    np.testing.assert_allclose(moved.level, base.level[list(order)], rtol=1e-9)


@settings(max_examples=15, deadline=None)
@given(kind=st.sampled_from(sorted(ESTIMATORS)), seed=st.integers(0, 2**16),
       bandwidth=st.sampled_from([None, 0, 3, 200]))
def test_sums_fed_in_pieces_equal_the_estimate_on_all_rows(kind, seed, bandwidth):
    """A file read in chunks feeds each trajectory's rows in pieces: the blocks must not move."""
    if kind != "hac" and bandwidth is not None:
        return
    data, fit = _reference()
    whole = covariance(kind, fit.G, fit.lam, fit.r, data.w, data.groups,
                       df_resid=fit.df_resid, bandwidth=bandwidth)
    rng = np.random.default_rng(seed)
    cuts = np.sort(rng.choice(np.arange(1, len(fit.r)), size=12, replace=False))
    z = np.column_stack([fit.G, fit.lam])

    def one_pass(lags):
        sums = ScoreSums(kind, fit.G.shape[1], len(SIZES), lags)
        for rows in np.split(np.arange(len(fit.r)), cuts):
            for j in np.unique(data.groups[rows]):
                mine = rows[data.groups[rows] == j]
                sums.add(int(j), z[mine], fit.r[mine], data.w[mine])
        return sums

    sums = one_pass(bandwidth)
    if sums.needs_bandwidth:
        sums = one_pass(sums.andrews_bandwidth())
    blocks, description, _ = sums.estimate(fit.df_resid, automatic=bandwidth is None)
    p = fit.G.shape[1]
    np.testing.assert_allclose(blocks[:, :p, :p].sum(axis=0), whole.theta, rtol=1e-10)
    np.testing.assert_allclose(blocks[:, p, p], whole.level, rtol=1e-10)
    assert description == whole.description


def test_covariance_arrays_are_read_only():
    data, fit = _reference()
    cov = _cov("hc", data, fit)
    with pytest.raises(ValueError, match="read-only"):
        cov.theta[0, 0] = 0.0


def _bandwidth(rho, sizes=SIZES, seed=3):
    data = _simulate(seed, sizes, rho=rho, rho_x=0.9, hetero=False)
    fit = _fit(data.A, data.b, data.w, data.groups)
    return bartlett_bandwidth(fit.G, fit.lam, fit.r, data.groups)


def test_bandwidth_grows_with_autocorrelation():
    independent, persistent = _bandwidth(0.0), _bandwidth(0.95)
    assert independent <= 3
    assert persistent >= 4 * max(independent, 3)


def test_bandwidth_is_capped_by_longest_trajectory():
    """Near-unit-root scores ask for ~60 lags; only 19 exist, in the longest trajectory."""
    sizes = (12, 15, 20)
    groups = np.repeat(np.arange(3), sizes)
    rng = np.random.default_rng(6)
    walk = np.concatenate([np.cumsum(rng.standard_normal(m)) for m in sizes])
    lam = 1.0 / np.repeat(sizes, sizes)
    assert bartlett_bandwidth(np.ones((len(groups), 1)), lam, walk, groups) == 19


def test_hac_keeps_lags_inside_trajectories():
    """A bandwidth longer than every trajectory still pairs rows of one trajectory only."""
    data, fit = _reference()
    one = _cov("hac", data, fit, bandwidth=400)
    blocks = []
    for j in range(len(SIZES)):
        rows = data.groups == j
        s = np.column_stack((fit.G[rows], fit.lam[rows])) * fit.r[rows, None]
        lag = np.abs(np.subtract.outer(np.arange(len(s)), np.arange(len(s))))
        kernel = np.clip(1 - lag / 401, 0, None)
        blocks.append(s.T @ kernel @ s)
    n = len(data.b)
    expected = n / fit.df_resid * np.sum(blocks, axis=0)
    np.testing.assert_allclose(one.theta, expected[:3, :3], rtol=1e-9)
    np.testing.assert_allclose(one.level, n / fit.df_resid * np.array([b[3, 3] for b in blocks]))


def test_hac_interval_covers_where_classical_does_not():
    """Monte Carlo: AR(1) errors (rho 0.5) and smooth regressors, 300 seeded replicates."""
    hits = {"hac": 0, "classical": 0}
    reps = 300
    for seed in range(reps):
        data = _simulate(1000 + seed, (250, 250), rho=0.5, rho_x=0.9, hetero=False, p=2)
        fit = _fit(data.A, data.b, data.w, data.groups)
        for kind in hits:
            cov = _cov(kind, data, fit)
            se = np.sqrt(np.diag(cov.theta))
            low, high = confidence_bounds(fit.theta, se, cov.df, 0.95)
            hits[kind] += int(low[0] <= THETA[0] <= high[0])
    assert 0.90 <= hits["hac"] / reps <= 0.99
    assert hits["classical"] / reps < 0.90


def test_bootstrap_matches_classical_on_independent_rows():
    data = _simulate(4, rho=0.0, rho_x=0.0, hetero=False)
    fit = _fit(data.A, data.b, data.w, data.groups)

    def refit(rows):
        return _fit(data.A[rows], data.b[rows], data.w[rows], data.groups[rows]).theta

    boot, n_failed, description = bootstrap(refit, data.groups, n_boot=300, seed=5)
    classical = _cov("classical", data, fit).theta
    assert n_failed == 0
    # mean variance ratio over the parameters: about 10% spread over seeds at this size
    ratio = np.trace(np.linalg.solve(classical, boot)) / len(fit.theta)
    assert 0.75 < ratio < 1.25
    assert "300 replicates" in description


def test_bootstrap_resamples_blocks_inside_each_trajectory():
    groups = np.repeat(np.arange(len(SIZES)), SIZES)
    seen = []

    def refit(rows):
        seen.append(rows)
        return np.array([rows.mean(), rows.std()])

    first = bootstrap(refit, groups, n_boot=20, seed=7, block_length=10)
    for rows in seen:
        np.testing.assert_array_equal(groups[rows], groups)
        steps = np.diff(rows)
        # a block continues with the next row, so at most one jump per 10 rows
        assert np.count_nonzero(steps != 1) <= len(rows) // 10 + len(SIZES)
    again = bootstrap(refit, groups, n_boot=20, seed=7, block_length=10)
    np.testing.assert_array_equal(first[0], again[0])


def test_bootstrap_skips_failed_replicates():
    calls = []

    def refit(rows):
        calls.append(rows)
        if len(calls) % 3 == 0:
            raise FitError("cannot determine a1: its column never varies")
        return np.array([rows[:5].sum(), rows[-5:].sum()], dtype=float)

    cov, n_failed, description = bootstrap(refit, np.zeros(50, dtype=int), n_boot=30, seed=0)
    assert n_failed == 10
    assert cov.shape == (2, 2)
    assert "10 failed" in description


def test_bootstrap_fails_when_most_replicates_fail():
    calls = []

    def refit(rows):
        calls.append(rows)
        if len(calls) % 2:
            raise FitError("cannot determine a1")
        return np.zeros(2)

    with pytest.raises(FitError, match=r"6 of 11 resampled fits .*cannot determine a1"):
        bootstrap(refit, np.zeros(40, dtype=int), n_boot=11, seed=0)


def test_bootstrap_lets_other_errors_through():
    def refit(rows):
        raise ZeroDivisionError("a bug")

    with pytest.raises(ZeroDivisionError, match="a bug"):
        bootstrap(refit, np.zeros(40, dtype=int), n_boot=5, seed=0)


def test_confidence_bounds_use_t_quantile_and_nan_for_unknown():
    low, high = confidence_bounds([1.0, 2.0, 3.0], [0.5, None, np.nan], df=np.inf, level=0.95)
    z = stats.norm.ppf(0.975)
    np.testing.assert_allclose([low[0], high[0]], [1 - 0.5 * z, 1 + 0.5 * z], rtol=1e-12)
    assert np.isnan(low[1:]).all() and np.isnan(high[1:]).all()
    low, high = confidence_bounds(2.0, None, df=3, level=0.9)
    assert np.isnan(low) and np.isnan(high)
    low, high = confidence_bounds(0.0, 1.0, df=3, level=0.9)
    np.testing.assert_allclose([low, high], [-2.353363, 2.353363], rtol=1e-6)  # t table


def _bad_call(**changes):
    data, fit = _reference()
    args = {
        "kind": "hac",
        "G": fit.G,
        "lam": fit.lam,
        "residuals": fit.r,
        "weights": data.w,
        "groups": data.groups,
        "df_resid": fit.df_resid,
    }
    args.update(changes)
    kind = args.pop("kind")
    return lambda: covariance(kind, **args)


def _noncontiguous():
    groups = _reference()[0].groups.copy()
    groups[:5] = 2
    return groups


def _nan_at(values, row):
    out = values.copy()
    out[row] = np.nan
    return out


BAD = [
    ({"kind": "HC1"}, "`kind` must be one of classical, hc, hac"),
    ({"G": np.zeros(400)}, r"`G` must have shape \(n, p\)"),
    ({"lam": np.ones(399)}, r"`lam` must have shape \(400,\)"),
    ({"residuals": _nan_at(np.zeros(400), 17)}, "`residuals` has non-finite values.*row 17"),
    ({"weights": np.r_[np.ones(399), 0.0]}, "`weights` must be positive, row 399"),
    ({"groups": np.zeros(400)}, "`groups` must hold integers"),
    ({"groups": np.repeat([1, 2, 3], SIZES)}, "number the trajectories 0..2"),
    ({"groups": _noncontiguous}, "`groups` must be contiguous"),
    ({"df_resid": 0}, "`df_resid` must be a positive integer"),
    ({"kind": "hc", "bandwidth": 3}, "`bandwidth` applies only to kind 'hac'"),
    ({"bandwidth": -1}, "`bandwidth` must be >= 0"),
    ({"kind": "hc", "units": np.arange(400)}, "`units` applies only to kind 'hac'"),
    ({"units": np.zeros(400, dtype=int)}, "each unit inside one trajectory"),
    ({"units": np.arange(400) + 1}, "must number the units 0..K-1"),
]


@pytest.mark.parametrize(("changes", "match"), BAD)
def test_covariance_rejects_bad_arguments(changes, match):
    changes = {key: value() if callable(value) else value for key, value in changes.items()}
    with pytest.raises(ValueError, match=match):
        _bad_call(**changes)()


def test_hac_units_of_single_rows_change_nothing():
    data, fit = _reference()
    plain = _cov("hac", data, fit, bandwidth=4)
    units = _cov("hac", data, fit, bandwidth=4, units=np.arange(len(data.b)))
    np.testing.assert_allclose(units.theta, plain.theta, rtol=1e-12)
    np.testing.assert_allclose(units.level, plain.level, rtol=1e-12)


def test_hac_on_units_is_newey_west_of_the_unit_sums():
    """Rows summed per unit, then the Bartlett kernel over units: written out by hand."""
    data, fit = _reference()
    units = _clusters(data.groups)  # consecutive blocks of rows in each trajectory
    lags = 2
    cov = _cov("hac", data, fit, bandwidth=lags, units=units)
    scores = np.column_stack((fit.G, fit.lam)) * fit.r[:, None]
    n_units = units.max() + 1
    sums = np.array([scores[units == u].sum(axis=0) for u in range(n_units)])
    owner = np.array([data.groups[units == u][0] for u in range(n_units)])
    fitted = len(data.b) - fit.df_resid
    factor = n_units / (n_units - fitted)
    p = fit.G.shape[1]
    theta = np.zeros((p, p))
    for j in np.unique(owner):
        s = sums[owner == j]
        meat = sum(max(0.0, 1 - abs(a - b) / (lags + 1)) * np.outer(s[a], s[b])
                   for a in range(len(s)) for b in range(len(s)))
        theta += factor * meat[:p, :p]
        np.testing.assert_allclose(cov.level[j], factor * meat[p, p], rtol=1e-9)
        np.testing.assert_allclose(cov.theta_level[j], factor * meat[p, :p], rtol=1e-9)
    np.testing.assert_allclose(cov.theta, theta, rtol=1e-9)
    assert f"{n_units} units" in cov.description


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"level": 1.0}, "`level` must be strictly between 0 and 1"),
        ({"df": 0}, "`df` must be positive"),
        ({"stderr": [-1.0]}, "`stderr` must be >= 0"),
    ],
)
def test_confidence_bounds_reject_bad_arguments(kwargs, match):
    args = {"estimate": [1.0], "stderr": [1.0], "df": 10, "level": 0.95, **kwargs}
    with pytest.raises(ValueError, match=match):
        confidence_bounds(**args)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_boot": 1}, "`n_boot` must be an integer >= 2"),
        ({"block_length": 0}, "`block_length` must be >= 1"),
        ({"groups": np.array([0, 1, 0])}, "`groups` must be contiguous"),
    ],
)
def test_bootstrap_rejects_bad_arguments_before_refitting(kwargs, match):
    def refit(rows):
        raise AssertionError("refit called before the arguments were checked")

    args = {"groups": np.zeros(10, dtype=int), "n_boot": 10, "seed": 0, **kwargs}
    with pytest.raises(ValueError, match=match):
        bootstrap(refit, **args)


@pytest.mark.parametrize("bandwidth", [None, 5])
def test_score_sums_keep_none_of_the_rows_they_were_fed(bandwidth):
    """A chunked fit feeds every row through: what the sums keep between pieces (the last
    score, the last cumulative sums of an open trajectory) must be copies, not views that
    hold each piece (50 pieces of 20,000 rows here, 32 MB)."""
    rng = np.random.default_rng(0)
    sums = ScoreSums("hac", 3, 50, bandwidth)
    tracemalloc.start()
    try:
        for j in range(50):
            z, r = rng.standard_normal((20_000, 4)), rng.standard_normal(20_000)
            sums.add(j, z, r, np.ones(20_000))
            del z, r
        kept, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert kept < 1_000_000


@pytest.mark.parametrize("kind", ["classical", "hc", "hac-bandwidth", "hac"])
@pytest.mark.parametrize("with_offset", [False, True])
def test_runs_fed_at_once_sum_as_fed_one_by_one(kind, with_offset):
    """`add_runs` (trajectories of one length seen first taken together) gives the sums of
    `add` run by run, over pieces that cut trajectories and lengths that differ."""
    from hamid.linear.uncertainty import ScoreSums

    rng = np.random.default_rng(5)
    lengths = [20, 1, 20, 7, 20, 33, 2, 20]
    group = np.repeat(np.arange(len(lengths)), lengths)
    n, p = len(group), 2
    z, r = rng.standard_normal((n, p + 1)), rng.standard_normal(n)
    w = rng.uniform(0.5, 2.0, n)
    offset = rng.standard_normal((n, p + 1)) if with_offset else None
    name, bandwidth = ("hac", None) if kind == "hac-bandwidth" else (kind, 3)
    at_once, one_by_one = (ScoreSums(name, p, len(lengths), bandwidth) for _ in range(2))
    for lo, hi in [(0, 45), (45, 90), (90, n)]:   # pieces that cut trajectories
        at_once.add_runs(group[lo:hi], z[lo:hi], r[lo:hi], w[lo:hi],
                         None if offset is None else offset[lo:hi])
        edges = [lo, *(lo + 1 + np.flatnonzero(np.diff(group[lo:hi]))), hi]
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            one_by_one.add(int(group[a]), z[a:b], r[a:b], w[a:b],
                           None if offset is None else offset[a:b])
    if kind == "hac-bandwidth":
        assert at_once.andrews_bandwidth() == one_by_one.andrews_bandwidth() > 0
        np.testing.assert_array_equal(at_once.sizes, one_by_one.sizes)
    else:
        found, _, _ = at_once.estimate(n - p)
        expected, _, _ = one_by_one.estimate(n - p)
        np.testing.assert_allclose(found, expected, rtol=1e-12, atol=1e-14)
        assert np.all(found != 0)
