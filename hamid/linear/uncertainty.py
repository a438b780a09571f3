"""Covariance of the fitted parameters and energy levels, and confidence bounds.

The fit eliminates the energy levels by weighted centring within each trajectory, so both
estimates are linear in the row errors e:

    theta_hat - theta = sum_i G_i e_i
    h_hat_j - h_j     = m_j - Abar_j (theta_hat - theta),   m_j = sum_{i in j} lam_i e_i

The solver hands over G (n, p) and lam (n,); this module estimates Cov(theta_hat),
Cov(m_j, theta_hat) and Var(m_j) from the residuals. Every estimator is a sandwich whose meat
is built from the augmented scores s_i = [G_i, lam_i] r_i. Rows of different trajectories are
never paired, so the meat is block-diagonal across trajectories and is computed one
trajectory at a time: nothing of size (n, p + J) is ever formed. The caller gets the
level's covariance from

    Var(h_j)          = level_j - 2 Abar_j . theta_level_j + Abar_j theta Abar_j^T
    Cov(h_j, theta)   = theta_level_j - Abar_j theta
    Cov(h_j, h_k)     = - Abar_j . theta_level_k - Abar_k . theta_level_j + Abar_j theta Abar_k^T

with Abar_j the weighted mean of the design rows of trajectory j.

Small-sample conventions (each checked against statsmodels' WLS on the full design with one
dummy column per trajectory, k = p + J columns, ``df_resid = n - k``):

- ``classical``: s^2 = sum w r^2 / df_resid (``cov_type="nonrobust"``);
- ``hc``: HC1, n / df_resid (``cov_type="HC1"``);
- ``hac``: Bartlett weights 1 - l / (L + 1), lags only within a trajectory, times
  n / df_resid (``cov_type="HAC"`` with ``use_correction=True`` for one trajectory,
  ``cov_type="hac-panel"`` with ``use_correction="hac"`` for several);
- ``hac`` with ``units``: the same on the series of unit sums of the scores, with
  K - (n - df_resid) residual degrees of freedom for K units.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.special import stdtrit

from hamid.errors import FitError

__all__ = [
    "DESCRIPTIONS",
    "ESTIMATORS",
    "Covariance",
    "ScoreSums",
    "UNITS_NOTE",
    "bartlett_bandwidth",
    "block_indices",
    "bootstrap",
    "confidence_bounds",
    "covariance",
    "fed_sums",
    "t_quantile",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]
Kind = Literal["classical", "hc", "hac"]
# An estimator's (J, p+1, p+1) meat blocks (scaled), its description and its t degrees of freedom.
_Estimate = tuple[FloatArray, str, int]

DESCRIPTIONS: dict[str, str] = {
    "classical": "classical (independent errors, variance proportional to 1/weight)",
    "hc": "heteroscedasticity robust (HC1)",
    "hac": "Newey-West (Bartlett kernel, bandwidth {bandwidth}{how}) within each trajectory",
    "bootstrap": (
        "moving-block bootstrap within each trajectory ({n_boot} replicates, "
        "block length {block}{failed})"
    ),
}

# Andrews (1991), eq. (6.2): Bartlett-kernel constant of the AR(1) plug-in bandwidth.
_ANDREWS_BARTLETT = 1.1447
# An AR(1) coefficient of exactly 1 makes the plug-in infinite; the cap on the bandwidth
# takes over well before this bound.
_RHO_MAX = 0.99


@dataclass(frozen=True)
class Covariance:
    """Covariance of the parameters and of the level errors m_j, with how it was made.

    Attributes
    ----------
    theta : ndarray, shape (p, p)
        Cov(theta_hat).
    theta_level : ndarray, shape (J, p)
        Cov(m_j, theta_hat), row j for trajectory j.
    level : ndarray, shape (J,)
        Var(m_j).
    kind : str
        The estimator's name, a key of `ESTIMATORS`.
    description : str
        One line for the report.
    df : int
        Degrees of freedom for t intervals.
    """

    theta: FloatArray
    theta_level: FloatArray
    level: FloatArray
    kind: str
    description: str
    df: int


@dataclass(frozen=True)
class _Problem:
    """Checked inputs, with each trajectory's row range."""

    G: FloatArray
    lam: FloatArray
    r: FloatArray
    w: FloatArray
    labels: IntArray
    starts: IntArray
    stops: IntArray
    df_resid: int

    @property
    def n(self) -> int:
        return self.G.shape[0]

    @property
    def p(self) -> int:
        return self.G.shape[1]

    @property
    def n_groups(self) -> int:
        return len(self.labels)

    def groups(self) -> Iterator[tuple[int, slice]]:
        """Helper yielding each trajectory's label and row slice."""
        for j, lo, hi in zip(self.labels, self.starts, self.stops, strict=True):
            yield int(j), slice(int(lo), int(hi))

    def z(self, rows: slice) -> FloatArray:
        """Helper returning the augmented influence rows [G_i, lam_i]."""
        return np.column_stack((self.G[rows], self.lam[rows]))


def _group_runs(groups: npt.ArrayLike, n: int) -> tuple[IntArray, IntArray, IntArray]:
    """Helper checking `groups` and returning each run's label, start and stop."""
    g = np.asarray(groups)
    if g.shape != (n,):
        raise ValueError(f"`groups` must have shape ({n},), got {g.shape}")
    if n == 0:
        raise ValueError("`groups` is empty: there are no rows")
    if not np.issubdtype(g.dtype, np.integer):
        raise ValueError(f"`groups` must hold integers, got dtype {g.dtype}")
    change = np.flatnonzero(g[1:] != g[:-1]) + 1
    starts = np.concatenate(([0], change)).astype(np.intp)
    stops = np.concatenate((change, [n])).astype(np.intp)
    labels = g[starts].astype(np.intp)
    if len(np.unique(labels)) != len(labels):
        raise ValueError("`groups` must be contiguous: a trajectory's rows appear in two runs")
    if labels.min() != 0 or labels.max() != len(labels) - 1:
        raise ValueError(
            f"`groups` must number the trajectories 0..{len(labels) - 1}, "
            f"got labels {labels.min()}..{labels.max()}"
        )
    return labels, starts, stops


def _float_vector(name: str, value: npt.ArrayLike, n: int) -> FloatArray:
    """Helper checking one row vector: shape (n,) and finite."""
    a = np.asarray(value, dtype=np.float64)
    if a.shape != (n,):
        raise ValueError(f"`{name}` must have shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"`{name}` has non-finite values (first at row {_first_bad(a)})")
    return a


def _first_bad(a: FloatArray) -> int:
    """Helper returning the first row holding a non-finite value."""
    return int(np.flatnonzero(~np.isfinite(a.reshape(len(a), -1)).all(axis=1))[0])


def _problem(
    G: npt.ArrayLike,
    lam: npt.ArrayLike,
    residuals: npt.ArrayLike,
    weights: npt.ArrayLike | None,
    groups: npt.ArrayLike,
    df_resid: int,
) -> _Problem:
    """Helper checking the arguments common to every estimator."""
    G = np.asarray(G, dtype=np.float64)
    if G.ndim != 2 or G.shape[1] == 0:
        raise ValueError(f"`G` must have shape (n, p) with p >= 1, got {G.shape}")
    n = G.shape[0]
    if not np.all(np.isfinite(G)):
        raise ValueError(f"`G` has non-finite values (first at row {_first_bad(G)})")
    lam = _float_vector("lam", lam, n)
    if np.any(lam < 0):
        raise ValueError(f"`lam` must be >= 0, got {lam.min()}")
    r = _float_vector("residuals", residuals, n)
    w = np.ones(n) if weights is None else _float_vector("weights", weights, n)
    if np.any(w <= 0):
        raise ValueError(f"`weights` must be positive, row {int(np.argmin(w))} is {w.min()}")
    labels, starts, stops = _group_runs(groups, n)
    if isinstance(df_resid, bool) or not isinstance(df_resid, int | np.integer) or df_resid < 1:
        raise ValueError(f"`df_resid` must be a positive integer, got {df_resid!r}")
    return _Problem(G=G, lam=lam, r=r, w=w, labels=labels, starts=starts, stops=stops,
                    df_resid=int(df_resid))


# Rows of trajectories of one length whose scores `ScoreSums.add_runs` takes at once.
_BATCH_ROWS = 1 << 14


class ScoreSums:
    """The per-trajectory sums an estimator needs, fed with rows piece by piece.

    The meat of every estimator is a sum over the rows of each trajectory, so it can be
    accumulated from pieces of rows (a file read in chunks) as well as from all rows at
    once; both give the same blocks. Feed each trajectory's rows in time order with `add`,
    a trajectory's pieces in sequence. Newey-West with the automatic bandwidth needs the
    rows twice: the first pass gives `andrews_bandwidth`, and the second feeds a
    `ScoreSums` made with that bandwidth.
    """

    def __init__(self, kind: str, p: int, n_groups: int, bandwidth: int | None = None) -> None:
        if kind not in ESTIMATORS:
            raise ValueError(f"`kind` must be one of {', '.join(ESTIMATORS)}, got {kind!r}")
        self.kind, self.p, self.bandwidth = kind, p, bandwidth
        k = p + 1
        self.meat = np.zeros((n_groups, k, k))
        self.sizes = np.zeros(n_groups, dtype=np.int64)
        self.weighted_squares = 0.0
        # Andrews' sums of lag-1 and lag-0 products, pooled over trajectories.
        self._lagged, self._square = np.zeros(k), np.zeros(k)
        self._last: dict[int, FloatArray] = {}
        # Newey-West: per open trajectory, the last L + 1 cumulative sums of the scores.
        self._tail: dict[int, FloatArray] = {}

    @property
    def needs_bandwidth(self) -> bool:
        """Whether this pass only finds the bandwidth (hac without one given)."""
        return self.kind == "hac" and self.bandwidth is None

    def add(self, j: int, z: FloatArray, r: FloatArray, w: FloatArray,
            offset: FloatArray | None = None) -> None:
        """Rows of trajectory `j` that follow its earlier ones: influence rows z = [G, lam],
        residuals r and weights w. `offset` is a part of each row's score z r that the
        residual does not carry (a corrected score's correction); the robust estimators
        add it, the classical one, which models the residuals alone, has no use for it."""
        if len(r) == 0:
            return
        self.sizes[j] += len(r)
        self.weighted_squares += float(w @ r**2)
        if self.kind == "classical":
            self.meat[j] += (z / w[:, None]).T @ z
            return
        s = z * r[:, None] if offset is None else z * r[:, None] + offset
        if self.kind == "hc":
            self.meat[j] += s.T @ s
        elif self.needs_bandwidth:
            previous = self._last.get(j)
            before = s[:-1] if previous is None else np.vstack([previous, s[:-1]])
            after = s[1:] if previous is None else s
            self._lagged += np.einsum("ij,ij->j", after, before)
            self._square += np.einsum("ij,ij->j", before, before)
            self._last[j] = s[-1].copy()   # not a view, which would keep all of s
        else:
            self._add_boxes(j, s)

    def add_runs(self, group: npt.NDArray[np.int64], z: FloatArray, r: FloatArray,
                 w: FloatArray, offset: FloatArray | None = None) -> None:
        """`add` for each run of rows of one trajectory in `group`; the rows of
        trajectories seen here first, of one length, all at once (5,000 trajectories of
        20 rows took a call each, a third of their fit)."""
        if len(r) == 0:
            return
        edges = np.flatnonzero(np.diff(group)) + 1
        starts, stops = np.r_[0, edges], np.r_[edges, len(group)]
        fresh = self.sizes[group[starts]] == 0
        batched: dict[int, list[int]] = {}
        for k, (start, stop) in enumerate(zip(starts.tolist(), stops.tolist(), strict=True)):
            if fresh[k]:
                batched.setdefault(stop - start, []).append(start)
            else:
                self.add(int(group[start]), z[start:stop], r[start:stop], w[start:stop],
                         None if offset is None else offset[start:stop])
        for length, firsts in batched.items():
            step = max(1, _BATCH_ROWS // length)   # the scores' copies stay bounded
            for k in range(0, len(firsts), step):
                first = firsts[k:k + step]
                a, m = first[0], len(first)
                if first[-1] == a + (m - 1) * length:   # runs side by side: views
                    rows: slice | npt.NDArray[np.intp] = slice(a, a + m * length)
                else:
                    rows = (np.array(first)[:, None] + np.arange(length)).ravel()
                self._add_fresh(group[first], *(x[rows].reshape(m, length, *x.shape[1:])
                                                for x in (z, r, w)),
                                None if offset is None else
                                offset[rows].reshape(m, length, offset.shape[1]))

    def _add_fresh(self, js: npt.NDArray[np.int64], z: FloatArray, r: FloatArray,
                   w: FloatArray, offset: FloatArray | None) -> None:
        """`add` of the first rows of trajectories `js`, of one length: z of shape
        (m, n, p + 1), r and w of shape (m, n)."""
        self.sizes[js] += r.shape[1]
        self.weighted_squares += float(np.sum(w * r**2))
        if self.kind == "classical":
            self.meat[js] += _gram(z / w[:, :, None], z)
            return
        s = z * r[:, :, None] if offset is None else z * r[:, :, None] + offset
        if self.kind == "hc":
            self.meat[js] += _gram(s, s)
        elif self.needs_bandwidth:
            self._lagged += np.einsum("mni,mni->i", s[:, 1:], s[:, :-1])
            self._square += np.einsum("mni,mni->i", s[:, :-1], s[:, :-1])
            for j, last in zip(js.tolist(), s[:, -1].copy(), strict=True):
                self._last[j] = last
        else:   # `_add_boxes` of each
            L, n = int(self.bandwidth or 0), s.shape[1]
            cum = np.concatenate([np.zeros((len(js), 1, s.shape[2])), np.cumsum(s, axis=1)],
                                 axis=1)
            end = np.arange(1, n + 1)
            box = cum[:, end] - cum[:, np.maximum(end - L - 1, 0)]
            self.meat[js] += _gram(box, box) / (L + 1)
            for j, tail in zip(js.tolist(), cum[:, max(n - L, 0):].copy(), strict=True):
                self._tail[j] = tail

    def _add_boxes(self, j: int, s: FloatArray) -> None:
        """Bartlett meat: sum_{t,u} (1 - |t-u|/(L+1))_+ s_t s_u^T of each trajectory.

        The Bartlett kernel is the self-convolution of a box of L + 1 samples, so the sum
        equals sum_k B_k B_k^T / (L + 1) over all (also partial) windows B_k of L + 1
        consecutive scores. Here the boxes ending at each new row; `close` adds those
        that run past the trajectory's last row.
        """
        L = int(self.bandwidth or 0)
        tail = self._tail.get(j, np.zeros((1, s.shape[1])))
        seen = int(self.sizes[j]) - len(s)           # rows of j before this piece
        first = max(seen - L, 0)                     # index of tail[0] in cum[0..]
        cum = np.vstack([tail, tail[-1] + np.cumsum(s, axis=0)])
        end = np.arange(seen + 1, seen + len(s) + 1)
        box = cum[end - first] - cum[np.maximum(end - L - 1, 0) - first]
        self.meat[j] += box.T @ box / (L + 1)
        self._tail[j] = cum[max(seen + len(s) - L, 0) - first:].copy()

    def close(self, j: int) -> None:
        """End trajectory `j` (hac: add the boxes that run past its last row)."""
        tail = self._tail.pop(j, None)
        if tail is None:
            return
        L = int(self.bandwidth or 0)
        n = int(self.sizes[j])
        # Boxes k = n-L .. n-1 reach from cum[max(k, 0)] to cum[n].
        starts = np.maximum(np.arange(n - L, n), 0) - max(n - L, 0)
        box = tail[-1] - tail[starts]
        self.meat[j] += box.T @ box / (L + 1)

    def andrews_bandwidth(self) -> int:
        """Andrews' AR(1) plug-in bandwidth from the first pass (see `bartlett_bandwidth`)."""
        usable = self._square > 0
        present = self.sizes[self.sizes > 0]
        if not np.any(usable):
            return 0
        rho = np.clip(self._lagged[usable] / self._square[usable], -_RHO_MAX, _RHO_MAX)
        # Andrews' weights w_a = sigma_a^-4 make every score column count alike, so that
        # the bandwidth does not depend on the units of the parameters or of the energy.
        alpha = np.sum(4 * rho**2 / ((1 - rho) ** 6 * (1 + rho) ** 2)) / np.sum(
            1 / (1 - rho) ** 4)
        bandwidth = math.ceil(_ANDREWS_BARTLETT * (alpha * float(np.median(present))) ** (1 / 3))
        return int(min(max(bandwidth, 0), int(present.max()) - 1))

    def covariance(self, df_resid: int, automatic: bool = False) -> Covariance:
        """The covariance from the sums (`automatic`: the bandwidth was Andrews')."""
        blocks, description, df = self.estimate(df_resid, automatic)
        return _covariance(blocks, self.kind, description, df)

    def estimate(self, df_resid: int, automatic: bool = False) -> _Estimate:
        """The scaled meat blocks, the description and the t degrees of freedom."""
        for j in list(self._tail):
            self.close(j)
        n = int(self.sizes.sum())
        if self.kind == "classical":
            return (self.weighted_squares / df_resid * self.meat, DESCRIPTIONS["classical"],
                    df_resid)
        if self.kind == "hc":
            return n / df_resid * self.meat, DESCRIPTIONS["hc"], df_resid
        description = DESCRIPTIONS["hac"].format(bandwidth=self.bandwidth,
                                                 how=", automatic" if automatic else "")
        return n / df_resid * self.meat, description, df_resid


def _gram(a: FloatArray, b: FloatArray) -> FloatArray:
    """Helper: a_m^T b_m of each of a stack of matrices (BLAS, where einsum is slower)."""
    return np.matmul(a.transpose(0, 2, 1), b)


def _feed(sums: ScoreSums, prob: _Problem) -> ScoreSums:
    """Helper feeding every trajectory's rows of `prob` at once."""
    for j, rows in prob.groups():
        sums.add(j, prob.z(rows), prob.r[rows], prob.w[rows])
        sums.close(j)
    return sums


def fed_sums(kind: str, p: int, n_groups: int, feed: Callable[[ScoreSums], object],
             bandwidth: int | None = None) -> tuple[ScoreSums, bool]:
    """The sums of estimator `kind` that `feed` fills with all rows, and whether the
    bandwidth is Andrews' automatic one: Newey-West without a `bandwidth` is fed twice,
    the first time to find it."""
    sums = ScoreSums(kind, p, n_groups, bandwidth)
    feed(sums)
    if not sums.needs_bandwidth:
        return sums, False
    automatic = ScoreSums(kind, p, n_groups, sums.andrews_bandwidth())
    feed(automatic)
    return automatic, True


def _estimate(prob: _Problem, kind: str, bandwidth: int | None) -> _Estimate:
    """Helper running one estimator on all rows."""
    sums, automatic = fed_sums(kind, prob.p, prob.n_groups, lambda s: _feed(s, prob),
                               bandwidth)
    return sums.estimate(prob.df_resid, automatic)


ESTIMATORS = ("classical", "hc", "hac")
# What a description adds when the scores of units of rows were summed first.
UNITS_NOTE = ", on the summed scores of {n} units of rows"


def _by_unit(prob: _Problem, units: npt.ArrayLike) -> _Problem:
    """Helper summing the scores of the rows of each unit into one row of a new problem.

    The new rows carry the summed scores as G (and lam) with residual 1 and weight 1, so
    every estimator sees the units as its rows; its residual degrees of freedom keep the
    number of fitted unknowns.
    """
    u = np.asarray(units)
    if u.shape != (prob.n,):
        raise ValueError(f"`units` must have shape ({prob.n},), got {u.shape}")
    if not np.issubdtype(u.dtype, np.integer) or u.min() != 0:
        raise ValueError("`units` must number the units 0..K-1 with integers")
    n_units = int(u.max()) + 1
    scores = np.column_stack((prob.G, prob.lam)) * prob.r[:, None]
    sums = np.stack([np.bincount(u, weights=column, minlength=n_units)
                     for column in scores.T], axis=1)
    row_labels = np.repeat(prob.labels, prob.stops - prob.starts)
    owner = np.full(n_units, -1)
    owner[u] = row_labels
    if np.any(owner < 0) or np.any(owner[u] != row_labels):
        raise ValueError("`units` must number 0..K-1 without gaps, each unit inside one "
                         "trajectory")
    labels, starts, stops = _group_runs(owner, n_units)
    fitted = prob.n - prob.df_resid
    if n_units - fitted < 1:
        raise ValueError(f"{n_units} units leave no degrees of freedom for {fitted} unknowns")
    return _Problem(G=sums[:, :prob.p], lam=sums[:, prob.p], r=np.ones(n_units),
                    w=np.ones(n_units), labels=labels, starts=starts, stops=stops,
                    df_resid=n_units - fitted)


def covariance(
    kind: Kind,
    G: npt.ArrayLike,
    lam: npt.ArrayLike,
    residuals: npt.ArrayLike,
    weights: npt.ArrayLike | None,
    groups: npt.ArrayLike,
    *,
    df_resid: int,
    bandwidth: int | None = None,
    units: npt.ArrayLike | None = None,
) -> Covariance:
    """Estimate the covariance of the parameters and of the level errors.

    Parameters
    ----------
    kind : {"classical", "hc", "hac"}
        The estimator, a key of `ESTIMATORS`.
    G : array_like, shape (n, p)
        Influence of each row's error on theta_hat.
    lam : array_like, shape (n,)
        Weight of each row in its trajectory's level, w_i / W_j (0 for rows with no level).
    residuals : array_like, shape (n,)
        Unweighted residuals b - a theta - h.
    weights : array_like, shape (n,), or None
        Positive row weights; None means all 1.
    groups : array_like of int, shape (n,)
        Trajectory of each row, 0..J-1; each trajectory's rows contiguous, in time order.
    df_resid : int
        Residual degrees of freedom, n minus the number of fitted unknowns (levels included).
    bandwidth : int, optional
        Highest lag for ``"hac"``; by default Andrews' plug-in (`bartlett_bandwidth`).
    units : array_like of int, shape (n,), optional
        For ``"hac"``: rows that share their errors (e.g. the rows of one weak-form
        window), numbered 0..K-1 in time order within each trajectory. Their scores are
        summed first, and the kernel runs over the series of unit sums.

    Returns
    -------
    Covariance
        Its blocks give Var(h_j) = level_j - 2 Abar_j . theta_level_j + Abar_j theta Abar_j^T.

    Raises
    ------
    ValueError
        If an argument has the wrong shape or value, or an option does not apply to `kind`.
    """
    if kind not in ESTIMATORS:
        raise ValueError(f"`kind` must be one of {', '.join(ESTIMATORS)}, got {kind!r}")
    prob = _problem(G, lam, residuals, weights, groups, df_resid)
    if bandwidth is not None:
        if kind != "hac":
            raise ValueError(f"`bandwidth` applies only to kind 'hac', not {kind!r}")
        if isinstance(bandwidth, bool) or not isinstance(bandwidth, int | np.integer):
            raise ValueError(f"`bandwidth` must be an integer, got {bandwidth!r}")
        if bandwidth < 0:
            raise ValueError(f"`bandwidth` must be >= 0, got {bandwidth}")
    if units is not None:
        if kind != "hac":
            raise ValueError(f"`units` applies only to kind 'hac', not {kind!r}")
        prob = _by_unit(prob, units)

    blocks, description, df = _estimate(prob, kind, bandwidth)
    if units is not None:
        description += UNITS_NOTE.format(n=prob.n)
    return _covariance(blocks, kind, description, df)


def _covariance(blocks: FloatArray, kind: str, description: str, df: int) -> Covariance:
    """Helper assembling a Covariance from the scaled meat blocks."""
    p = blocks.shape[1] - 1
    theta = blocks[:, :p, :p].sum(axis=0)
    theta = (theta + theta.T) / 2  # exact symmetry, lost in summation order
    theta_level = blocks[:, p, :p].copy()
    level = blocks[:, p, p].copy()
    for array in (theta, theta_level, level):
        array.setflags(write=False)
    return Covariance(theta, theta_level, level, kind, description, int(df))


def bartlett_bandwidth(
    G: npt.ArrayLike,
    lam: npt.ArrayLike,
    residuals: npt.ArrayLike,
    groups: npt.ArrayLike,
) -> int:
    """Choose the Newey-West bandwidth from the autocorrelation of the scores.

    Andrews' (1991) AR(1) plug-in for the Bartlett kernel: an AR(1) coefficient rho_a is
    fitted to each score column [G, lam] r, pooling lag-1 pairs within trajectories (never
    across), and

        alpha = sum 4 rho^2 / ((1 - rho)^6 (1 + rho)^2) / sum 1 / (1 - rho)^4,
        L = ceil(1.1447 (alpha n_eff)^(1/3)),

    with n_eff the median trajectory length. This is Andrews' formula with weights
    w_a = sigma_a^-4, so that L does not change when a parameter's units do. rho is clipped
    to +-0.99, and L to 0..(longest trajectory - 1): a longer lag adds no pair of rows, and
    a short trajectory does not switch the correction off for the long ones.

    Parameters
    ----------
    G : array_like, shape (n, p)
        Influence of each row's error on theta_hat.
    lam : array_like, shape (n,)
        Weight of each row in its trajectory's level.
    residuals : array_like, shape (n,)
        Unweighted residuals.
    groups : array_like of int, shape (n,)
        Trajectory of each row, contiguous.

    Returns
    -------
    int
        The highest lag with nonzero weight.
    """
    prob = _problem(G, lam, residuals, None, groups, 1)
    return _feed(ScoreSums("hac", prob.p, prob.n_groups), prob).andrews_bandwidth()


def t_quantile(df: float, level: float) -> float:
    """The two-sided critical value of Student's t at `level` (scipy.special: the
    distribution's inverse without importing scipy.stats, which costs a second at start)."""
    return float(stdtrit(df, (1 + level) / 2))


def confidence_bounds(
    estimate: npt.ArrayLike,
    stderr: npt.ArrayLike | None,
    df: float,
    level: float,
) -> tuple[FloatArray, FloatArray]:
    """Two-sided t confidence bounds; an unknown standard error gives NaN bounds.

    Parameters
    ----------
    estimate : array_like
        Estimates.
    stderr : array_like or None
        Standard errors, broadcastable to `estimate`; None or NaN where unknown.
    df : float
        Degrees of freedom of the t distribution (``inf`` for the normal).
    level : float
        Confidence level, strictly between 0 and 1.

    Returns
    -------
    low, high : ndarray
        Bounds with the broadcast shape of `estimate` and `stderr`.

    Examples
    --------
    >>> low, high = confidence_bounds([1.0, 2.0], [0.1, None], df=10, level=0.95)
    >>> round(float(low[0]), 4), bool(np.isnan(high[1]))
    (0.7772, True)
    """
    if not 0 < level < 1:
        raise ValueError(f"`level` must be strictly between 0 and 1, got {level!r}")
    if not df > 0:
        raise ValueError(f"`df` must be positive, got {df!r}")
    est = np.asarray(estimate, dtype=np.float64)
    # dtype float64 turns None entries into NaN
    se = np.full_like(est, np.nan) if stderr is None else np.asarray(stderr, dtype=np.float64)
    if np.any(se < 0):
        raise ValueError(f"`stderr` must be >= 0, got {np.nanmin(se)}")
    half = t_quantile(df, level) * se
    return est - half, est + half


def block_indices(
    rng: np.random.Generator, starts: IntArray, stops: IntArray, lengths: IntArray
) -> IntArray:
    """One moving-block resample of the rows, trajectory by trajectory: rows `starts[j]` to
    `stops[j]` rebuilt to their length from blocks of `lengths[j]` rows drawn with
    replacement."""
    parts = []
    for lo, hi, block in zip(starts, stops, lengths, strict=True):
        size = hi - lo
        n_blocks = -(-size // block)
        first = rng.integers(0, size - block + 1, size=n_blocks)
        parts.append(lo + (first[:, None] + np.arange(block)).ravel()[:size])
    return np.concatenate(parts)


def bootstrap(
    refit: Callable[[IntArray], npt.ArrayLike],
    groups: npt.ArrayLike,
    *,
    n_boot: int,
    seed: int | None,
    block_length: int | None = None,
) -> tuple[FloatArray, int, str]:
    """Estimate a covariance by refitting on moving-block resamples of each trajectory.

    Each replicate rebuilds every trajectory to its own length from contiguous blocks of its
    own rows, drawn with replacement, so the correlation within a block is kept and rows of
    different trajectories are never mixed.

    Parameters
    ----------
    refit : callable
        ``refit(indices)`` fits the rows ``indices`` (shape (n,), into the original rows,
        each trajectory's rows contiguous and in order of the original trajectories) and
        returns the estimate vector. A `FitError` marks a failed replicate.
    groups : array_like of int, shape (n,)
        Trajectory of each row, contiguous.
    n_boot : int
        Number of replicates, at least 2.
    seed : int or None
        Seed for `numpy.random.default_rng`.
    block_length : int, optional
        Block length for every trajectory (shortened to a trajectory's length); by default
        ceil(n_j^(1/3)) for a trajectory of n_j rows.

    Returns
    -------
    cov : ndarray, shape (p, p)
        Sample covariance (ddof 1) of the successful replicates.
    n_failed : int
        Replicates whose refit raised `FitError`.
    description : str
        One line for the report.

    Raises
    ------
    FitError
        If more than half of the replicates (or all but one) fail.
    """
    g = np.asarray(groups)
    if g.ndim != 1:
        raise ValueError(f"`groups` must have shape (n,), got {g.shape}")
    _, starts, stops = _group_runs(g, g.shape[0])
    if isinstance(n_boot, bool) or not isinstance(n_boot, int | np.integer) or n_boot < 2:
        raise ValueError(f"`n_boot` must be an integer >= 2, got {n_boot!r}")
    sizes = stops - starts
    if block_length is None:
        lengths = np.ceil(sizes ** (1 / 3)).astype(np.intp)
        block = "ceil(n^(1/3)) per trajectory"
    else:
        if isinstance(block_length, bool) or not isinstance(block_length, int | np.integer):
            raise ValueError(f"`block_length` must be an integer, got {block_length!r}")
        if block_length < 1:
            raise ValueError(f"`block_length` must be >= 1, got {block_length}")
        lengths = np.full(len(sizes), block_length, dtype=np.intp)
        block = str(block_length)
    lengths = np.minimum(lengths, sizes)

    rng = np.random.default_rng(seed)
    estimates: list[FloatArray] = []
    n_failed = 0
    last_error: FitError | None = None
    for _ in range(n_boot):
        indices = block_indices(rng, starts, stops, lengths)
        try:
            estimate = np.asarray(refit(indices), dtype=np.float64)
        except FitError as exc:
            n_failed += 1
            last_error = exc
            continue
        if estimates and estimate.shape != estimates[0].shape:
            raise ValueError(
                f"`refit` returned shape {estimate.shape}, earlier {estimates[0].shape}"
            )
        estimates.append(estimate.ravel())
    if 2 * n_failed > n_boot or len(estimates) < 2:
        raise FitError(
            f"bootstrap failed: {n_failed} of {n_boot} resampled fits could not determine "
            f"the parameters (last: {last_error})"
        ) from last_error
    cov = np.atleast_2d(np.cov(np.stack(estimates), rowvar=False))
    failed = f", {n_failed} failed" if n_failed else ""
    description = DESCRIPTIONS["bootstrap"].format(n_boot=n_boot, block=block, failed=failed)
    return cov, n_failed, description
