"""Which terms are in the energy: best-subset search over the linear rows of a library
(docs/method.md, "Model selection").

The rows of the whole library are built and weighted once, as a fit of every term would
weight them; every subset is then scored from the triangular factor of those rows (a QR of
the subset's columns of the factor, never a refit of the rows), by BIC or AIC on the
effective number of rows, or by blocked cross-validation over windows. Up to
`EXHAUSTIVE_TERMS` free terms every subset is scored; beyond, a greedy forward-backward
path. Pure arrays in and out: no files, no models.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import numpy.typing as npt

from hamid.data.records import runs
from hamid.linear import estimate, uncertainty
from hamid.linear.design import WINDOW_STEP, Block
from hamid.options import SELECTION_CRITERIA as CRITERIA

__all__ = ["CRITERIA", "EXHAUSTIVE_TERMS", "MARGIN", "Candidate", "Design", "Ranking", "collinear",
           "effective_fraction", "inclusion", "search"]

# Up to this many free terms every subset is scored (2^20 subsets take about 10 s).
EXHAUSTIVE_TERMS = 20
# Residuals below this fraction of the rows' rms are at the accuracy of the rows
# themselves (the weak-form quadrature is O(dt^6): 1e-12 to 1e-9 of the rows on clean
# simulated records): models that fit that well tie, and the penalty decides.
RESIDUAL_FLOOR = 1e-8
# A term whose unit column lies this close to the span of simpler ones cannot be told
# apart from them on the data (a variance inflation factor above 1e12).
COLLINEAR = 1e-6
CV_FOLDS = 5
# Differences of BIC or AIC below 2 are "not worth more than a bare mention" (Kass and
# Raftery 1995): the fewest terms within this margin of the lowest value are chosen.
MARGIN = 2.0
SHOWN = 10   # candidate models kept in the ranking
_BATCH = 4096  # subsets scored together (memory: _BATCH * (p + 1) * k doubles)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]


@dataclass(frozen=True)
class Design:
    """The library's rows as the search needs them.

    M : shape (n_rows, p + 1): the weighted rows with the levels eliminated (centred within
        each trajectory), the p term columns scaled to unit norm, then the known side.
    unit : shape (n_rows,): the unit of each row (its weak-form window, or its sample for
        energy rows), numbered in time order within each trajectory; units are what
        cross-validation holds out and the bootstrap resamples.
    unit_group : shape (n_units,): the trajectory of each unit.
    gap : units on either side of a held-out block that share samples with it.
    fraction : effective rows per row (`effective_fraction`).
    floor : the residual variance below which models tie (`RESIDUAL_FLOOR`).
    """

    M: FloatArray
    unit: IntArray
    unit_group: IntArray
    gap: int
    fraction: float
    floor: float

    @classmethod
    def of(cls, fit: estimate.Solved, blocks: Sequence[Block], fraction: float) -> Design:
        """The design of a least-squares fit of `blocks` (every term free)."""
        A, b = fit.centred.arrays()
        M = np.column_stack([A / np.linalg.norm(A, axis=0), b])
        unit, unit_group = estimate.resampling_units(blocks)
        windows = len(blocks) > 1 or not blocks[0].has_level
        gap = round(1 / WINDOW_STEP) - 1 if windows else 0
        return cls(M, unit, unit_group, gap, fraction,
                   RESIDUAL_FLOOR**2 * float(np.mean(b**2)))

    @property
    def n_rows(self) -> int:
        return self.M.shape[0]

    @property
    def n_terms(self) -> int:
        return self.M.shape[1] - 1

    @property
    def n_effective(self) -> float:
        return self.fraction * self.n_rows

    @cached_property
    def R(self) -> FloatArray:
        """The triangular factor of M: every subset's least squares is one of R's."""
        return np.linalg.qr(self.M, mode="r")

    def resampled(self, units: IntArray) -> Design:
        """The design of the rows of `units`, in that order (a bootstrap replicate)."""
        by_unit = np.argsort(self.unit, kind="stable")
        first = np.searchsorted(self.unit[by_unit], np.arange(len(self.unit_group) + 1))
        rows = np.concatenate([by_unit[first[u]:first[u + 1]] for u in units])
        renumbered = np.repeat(np.arange(len(units)), first[units + 1] - first[units])
        return replace(self, M=self.M[rows], unit=renumbered,
                       unit_group=self.unit_group[units])


def effective_fraction(fit: estimate.Solved, blocks: list[Block],
                       window_group: IntArray | None) -> float:
    """Effective rows per row: how much less the rows tell than as many independent ones.

    The rows of overlapping windows share samples, so a least-squares fit of them gains
    more from an extra term than independent rows would: its likelihood ratio is inflated
    by the ratio of the parameter's ``hac`` variance, which sees the correlation, to its
    classical variance, which does not. The fraction is one over the mean of that ratio
    over the parameters of the whole library, at most 1.
    """
    hac = estimate.covariance("hac", fit, blocks, window_group).theta
    classical = estimate.covariance("classical", fit, blocks, window_group).theta
    inflation = float(np.max(np.diag(hac) / np.diag(classical)))
    return min(1.0, 1.0 / inflation) if math.isfinite(inflation) and inflation > 0 else 1.0


def collinear(A: FloatArray, order: Sequence[int]) -> list[tuple[int, list[int]]]:
    """Columns of `A` that cannot be told apart from simpler ones.

    The columns are taken in `order` (simplest first); one whose unit column lies within
    `COLLINEAR` of the span of the columns kept before it is dropped. Returns each dropped
    column with the kept columns it is (nearly) a combination of.
    """
    unit = A / np.linalg.norm(A, axis=0)
    kept: list[int] = []
    dropped = []
    for j in order:
        if kept:
            coef, *_ = np.linalg.lstsq(unit[:, kept], unit[:, j], rcond=None)
            distance = float(np.linalg.norm(unit[:, kept] @ coef - unit[:, j]))
            if distance < COLLINEAR:
                big = np.abs(coef) >= 1e-3 * np.max(np.abs(coef))
                dropped.append((j, [k for k, b in zip(kept, big, strict=True) if b]))
                continue
        kept.append(j)
    return dropped


@dataclass(frozen=True, kw_only=True)
class Candidate:
    """A scored subset: its columns, criterion value, residual variance per row relative
    to that of the whole library, and margin: by how much a subset of fewer columns may
    score worse and still be preferred (`MARGIN` for BIC and AIC, one standard error of
    the cross-validated error for CV)."""

    columns: tuple[int, ...]
    score: float
    variance: float
    margin: float


@dataclass(frozen=True, kw_only=True)
class Ranking:
    """The best subsets, best first, the one chosen, and how they were found."""

    candidates: tuple[Candidate, ...]
    chosen: Candidate
    exhaustive: bool
    evaluated: int


Scores = tuple[FloatArray, FloatArray, FloatArray]
Scorer = Callable[[IntArray], Scores]


def search(design: Design, forced: Sequence[int], free: Sequence[int],
           criterion: str) -> Ranking:
    """The subsets of the `free` columns (each with every `forced` one) ranked by the
    criterion: "bic", "aic" or "cv"; at least one column in each.

    The chosen subset is the one with the fewest columns among those within the best
    one's margin of it (2 for BIC and AIC; one standard error of the cross-validated
    error, the one-standard-error rule, for CV), the best of them if several have as few.
    """
    score = _scorer(design, criterion)
    exhaustive = len(free) <= EXHAUSTIVE_TERMS
    found, count = (_exhaustive if exhaustive else _stepwise)(score, forced, free)
    # ties (models at the residual floor) go to the fewer terms
    ranked = sorted(found, key=lambda c: (c.score, len(c.columns)))
    chosen = min((c for c in ranked if c.score <= ranked[0].score + ranked[0].margin),
                 key=lambda c: (len(c.columns), c.score))
    return Ranking(candidates=tuple(ranked[:SHOWN]), chosen=chosen, exhaustive=exhaustive,
                   evaluated=count)


def _scorer(design: Design, criterion: str) -> Scorer:
    """The criterion of subsets of columns (shape (m, k), k the same for all), their
    residual variance per row relative to the whole library's, and their margin."""
    n, R = design.n_rows, design.R
    scale = max(float(R[-1, -1]) ** 2 / max(n - design.n_terms, 1), np.finfo(float).tiny)

    def variance(rss: FloatArray, k: int) -> FloatArray:
        return rss / max(n - k, 1) / scale

    if criterion == "cv":
        folds = _folds(design)

        def cross_validated(subsets: IntArray) -> Scores:
            errors = np.array([_prediction_error(train, test, subsets) / size
                               for train, test, size in folds])
            sizes = np.array([size for _, _, size in folds])
            mean = np.maximum(sizes @ errors / sizes.sum(), design.floor)
            # one standard error of the mean over the folds
            spread = np.std(errors, axis=0, ddof=1) / math.sqrt(len(folds))
            return mean, variance(_rss(R, subsets), subsets.shape[1]), spread

        return cross_validated
    n_eff = design.n_effective
    penalty = math.log(n_eff) if criterion == "bic" else 2.0

    def information(subsets: IntArray) -> Scores:
        rss = _rss(R, subsets)
        k = subsets.shape[1]
        return (n_eff * np.log(np.maximum(rss / n, design.floor)) + penalty * k,
                variance(rss, k), np.full(len(subsets), MARGIN))

    return information


def _batches(subsets: IntArray) -> list[IntArray]:
    return [subsets[i:i + _BATCH] for i in range(0, len(subsets), _BATCH)]


def _rss(R: FloatArray, subsets: IntArray) -> FloatArray:
    """Residual sum of squares of each subset's least squares on the rows factored by R."""
    y = R[:, -1]
    if subsets.shape[1] == 0:
        return np.full(len(subsets), float(y @ y))
    out = []
    for part in _batches(subsets):
        Q = np.linalg.qr(np.moveaxis(R[:, part], 0, 1))[0]          # (m, q, k)
        # the residual itself, not |y|^2 - |Q'y|^2, which cancels when the fit is close
        r = y - np.einsum("mik,mk->mi", Q, np.einsum("mik,i->mk", Q, y))
        out.append(np.einsum("mi,mi->m", r, r))
    return np.concatenate(out)


def _prediction_error(train: FloatArray, test: FloatArray, subsets: IntArray) -> FloatArray:
    """Squared error on the rows factored by `test` of each subset fitted on `train`'s."""
    y = test[:, -1]
    if subsets.shape[1] == 0:
        return np.full(len(subsets), float(y @ y))
    out = []
    for part in _batches(subsets):
        Q, Rk = np.linalg.qr(np.moveaxis(train[:, part], 0, 1))
        theta = np.linalg.solve(Rk, np.einsum("mik,i->mk", Q, train[:, -1])[..., None])
        e = np.einsum("mik,mk->mi", np.moveaxis(test[:, part], 0, 1), theta[..., 0]) - y
        out.append(np.einsum("mi,mi->m", e, e))
    return np.concatenate(out)


def _folds(design: Design) -> list[tuple[FloatArray, FloatArray, int]]:
    """(training factor, test factor, test rows) of each fold: `CV_FOLDS` contiguous blocks of each
    trajectory's units, held out in turn; the units that share samples with a held-out
    block (`gap` on either side) are left out of its training rows."""
    fold = np.empty(len(design.unit_group), dtype=np.intp)
    position = np.empty(len(design.unit_group), dtype=np.intp)
    for _, start, stop in runs(design.unit_group):
        fold[start:stop] = np.arange(stop - start) * CV_FOLDS // (stop - start)
        position[start:stop] = np.arange(stop - start)
    out = []
    for f in range(CV_FOLDS):
        held = fold == f
        near = held.copy()
        for _, start, stop in runs(design.unit_group):
            inside = np.flatnonzero(held[start:stop])
            if inside.size:
                lo, hi = inside[0] - design.gap, inside[-1] + design.gap
                near[start:stop] |= (position[start:stop] >= lo) & (position[start:stop] <= hi)
        test, train = held[design.unit], ~near[design.unit]
        if test.any() and train.any():
            out.append((np.linalg.qr(design.M[train], mode="r"),
                        np.linalg.qr(design.M[test], mode="r"), int(test.sum())))
    return out


def _exhaustive(score: Scorer, forced: Sequence[int],
                free: Sequence[int]) -> tuple[list[Candidate], int]:
    """The best `SHOWN` subsets of each size, and how many subsets were scored."""
    found, count = [], 0
    for k in range(0 if forced else 1, len(free) + 1):
        combos = list(itertools.combinations(free, k))
        chosen = np.array(combos, dtype=np.intp).reshape(len(combos), k)
        subsets = np.column_stack([np.broadcast_to(np.asarray(forced, dtype=np.intp),
                                                   (len(chosen), len(forced))), chosen])
        values, variances, margins = score(subsets)
        best = np.argsort(values, kind="stable")[:SHOWN]
        found += [Candidate(columns=tuple(sorted(subsets[i].tolist())), score=float(values[i]),
                            variance=float(variances[i]), margin=float(margins[i]))
                  for i in best]
        count += len(subsets)
    return found, count


def _stepwise(score: Scorer, forced: Sequence[int],
              free: Sequence[int]) -> tuple[list[Candidate], int]:
    """A greedy forward-backward path: from the forced columns (or the best single one),
    take the best of adding or removing one free column while the criterion falls."""
    seen: dict[tuple[int, ...], Candidate] = {}

    def evaluate(sets: list[tuple[int, ...]]) -> None:
        new = sorted({s for s in sets if s not in seen}, key=len)
        for _, same in itertools.groupby(new, key=len):
            group = list(same)
            scored = score(np.array(group, dtype=np.intp).reshape(len(group), -1))
            seen.update({s: Candidate(columns=s, score=float(value), variance=float(variance),
                                      margin=float(margin))
                         for s, value, variance, margin in zip(group, *scored, strict=True)})

    current = tuple(sorted(forced))
    if not current:
        evaluate([(j,) for j in free])
        current = min(seen.values(), key=lambda c: c.score).columns
    evaluate([current])
    while True:
        moves = [tuple(sorted((*current, j))) for j in free if j not in current]
        moves += [tuple(c for c in current if c != j) for j in current
                  if j in free and len(current) > 1]
        evaluate(moves)
        best = min((seen[m] for m in moves), key=lambda c: c.score, default=None)
        if best is None or best.score >= seen[current].score:
            return list(seen.values()), len(seen)
        current = best.columns


def inclusion(design: Design, forced: Sequence[int], free: Sequence[int], criterion: str,
              replicates: int, seed: int | None,
              progress: Callable[[str], None] | None = None) -> FloatArray:
    """How often each free column is chosen in the searches of moving-block bootstrap
    replicates of the units (within trajectories, blocks of ceil(n^(1/3)) units)."""
    spans = runs(design.unit_group)
    starts = np.array([s for _, s, _ in spans], dtype=np.intp)
    stops = np.array([e for _, _, e in spans], dtype=np.intp)
    lengths = np.minimum(np.ceil((stops - starts) ** (1 / 3)).astype(np.intp), stops - starts)
    rng = np.random.default_rng(seed)
    counts = np.zeros(len(free))
    for r in range(replicates):
        units = uncertainty.block_indices(rng, starts, stops, lengths)
        best = search(design.resampled(units), forced, free, criterion).chosen.columns
        counts += [j in best for j in free]
        if progress is not None:
            progress(f"bootstrap replicate {r + 1} of {replicates}")
    return counts / replicates
