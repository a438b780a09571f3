"""Linear least squares by SVD of the column-scaled design, never the normal equations.

Energy levels are eliminated by weighted centring within each trajectory (Frisch-Waugh-
Lovell), so a fit with a thousand trajectories still solves for the parameters alone, and
the levels are recovered afterwards.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.data.records import runs
from hamid.errors import FitError
from hamid.linear.design import Block

__all__ = ["Centred", "Conditioning", "Factor", "Solution", "centred_piece", "conditioning",
           "factor_conditioning", "level_means", "solve", "solve_adjusted", "solve_factor"]

# A scaled singular value below this (a condition number above 1e10) leaves a direction
# undetermined at double precision for any data with noise in them.
_RANK_TOLERANCE = 1e-10
# A term whose variation within trajectories is below this fraction of its size is
# constant up to rounding.
_VARIES = 1e-9


# Rows are centred, weighted and factored this many at a time: the copies a fit in
# memory makes stay small however long the record (one piece: the whole rows at once).
PIECE_ROWS = 1 << 16


@dataclass(frozen=True)
class Centred:
    """Blocks stacked as weighted, level-free rows, sqrt(w) (A - mean_j A) and
    sqrt(w) (b - mean_j b), made a piece of rows at a time (`pieces`), not held."""

    blocks: tuple[Block, ...]
    level_means_A: npt.NDArray[np.float64]  # (J, p) weighted mean of A per trajectory
    level_means_b: npt.NDArray[np.float64]  # (J,)
    raw_norms: npt.NDArray[np.float64]      # (p,) column norms before centring
    means: tuple[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None, ...]

    @classmethod
    def of(cls, blocks: Sequence[Block], n_groups: int) -> Centred:
        """The blocks, each trajectory's means in those that carry a level."""
        p = blocks[0].A.shape[1]
        raw_sq = np.zeros(p)
        means_A, means_b = np.zeros((n_groups, p)), np.zeros(n_groups)
        means = []
        for block in blocks:
            raw_sq += np.einsum("i,ij,ij->j", block.weight, block.A, block.A)
            if block.has_level:
                means_A, means_b, _ = level_means(block, n_groups)
            means.append((means_A, means_b) if block.has_level else None)
        return cls(tuple(blocks), means_A, means_b, np.sqrt(raw_sq), tuple(means))

    @property
    def n_rows(self) -> int:
        return sum(block.n_rows for block in self.blocks)

    def pieces(self) -> Iterator[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64],
                                       npt.NDArray[np.float64]]]:
        """The centred weighted rows (A, b) and sqrt(w), at least `PIECE_ROWS` rows at a
        time (but the last), the blocks one after another; rows that fit in one piece are
        one piece, the arithmetic of all rows at once."""
        held: list[tuple[Any, Any, Any]] = []
        for block, means in zip(self.blocks, self.means, strict=True):
            for start in range(0, block.n_rows, PIECE_ROWS):
                held.append(centred_piece(block.slice(start, start + PIECE_ROWS), means))
                if sum(len(part[1]) for part in held) >= PIECE_ROWS:
                    yield tuple(_stacked(list(parts)) for parts in zip(*held, strict=True))
                    held = []
        if held:
            yield tuple(_stacked(list(parts)) for parts in zip(*held, strict=True))

    def arrays(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """All the centred weighted rows, A and b."""
        A, b, _ = zip(*self.pieces(), strict=True)
        return _stacked(list(A)), _stacked(list(b))

    def influence(self, inverse: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """G = sqrt(w) (centred A) @ inverse, shape (n_rows, p): theta - theta_true = G.T @ e
        for row errors e (`Solution`)."""
        return _stacked([sw[:, None] * (A @ inverse) for A, _, sw in self.pieces()])


def centred_piece(block: Block, means: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]
                  | None) -> tuple[npt.NDArray[np.float64], ...]:
    """Rows weighted and centred on their trajectories' `means` of A and b (None: rows
    without a level): sqrt(w) (A - mean_j A), sqrt(w) (b - mean_j b) and sqrt(w)."""
    A, b = block.A, block.b
    if means is not None:
        A, b = A - means[0][block.group], b - means[1][block.group]
    sw = np.sqrt(block.weight)
    if np.any(sw != 1.0):   # unit weights (the common case) need no product
        A, b = A * sw[:, None], b * sw
    return A, b, sw


def level_means(block: Block, n_groups: int) -> tuple[npt.NDArray[np.float64], ...]:
    """Weighted means of A and b in each trajectory, and 1 / each trajectory's weight.

    A trajectory with no rows here (too short for a window) has no level: NaN.
    """
    w, p = block.weight, block.A.shape[1]
    W = np.bincount(block.group, weights=w, minlength=n_groups)
    inverse = np.divide(1.0, W, out=np.full(n_groups, np.nan), where=W > 0)
    means_b = np.bincount(block.group, weights=w * block.b, minlength=n_groups) * inverse
    means_A = np.stack([np.bincount(block.group, weights=w * block.A[:, k],
                                    minlength=n_groups) for k in range(p)],
                       axis=-1).reshape(n_groups, p) * inverse[:, None]
    return means_A, means_b, inverse


def _stacked(parts: list[npt.NDArray[np.float64]]) -> npt.NDArray[np.float64]:
    """The parts one after another; a single part as it is, without a copy."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


class Factor:
    """Triangular factors of the weighted rows, accumulated piece by piece (tall-skinny QR).

    Each trajectory's level rows give R_j of [sqrt(w), sqrt(w) A, sqrt(w) b]: its lower
    right block is the factor of the rows centred within the trajectory, so the levels are
    eliminated without a pass to find the means first. Rows without a level (weak form)
    share one factor of [sqrt(w) A, sqrt(w) b]. Feeding the rows at once or in chunks
    gives the same factors, up to rounding.
    """

    def __init__(self, p: int, n_groups: int) -> None:
        self.p = p
        self.level: list[npt.NDArray[np.float64] | None] = [None] * n_groups
        self.free: npt.NDArray[np.float64] | None = None
        self.weighted_A = np.zeros((n_groups, p))
        self.weighted_b = np.zeros(n_groups)
        self.total_weight = np.zeros(n_groups)
        self.raw_squares = np.zeros(p)
        self.n_rows = 0

    def grow(self, n_groups: int) -> None:
        """Make room for trajectories up to `n_groups` (a chunked read finds them as it goes)."""
        extra = n_groups - len(self.level)
        if extra > 0:
            self.level += [None] * extra
            self.weighted_A = np.vstack([self.weighted_A, np.zeros((extra, self.p))])
            self.weighted_b = np.concatenate([self.weighted_b, np.zeros(extra)])
            self.total_weight = np.concatenate([self.total_weight, np.zeros(extra)])

    def add(self, block: Block) -> None:
        """Rows of any trajectories, each one's after its earlier rows."""
        if block.n_rows:
            self.grow(int(block.group.max()) + 1)
        sw = np.sqrt(block.weight)
        rows = np.column_stack([block.A, block.b]) * sw[:, None]
        self.n_rows += block.n_rows
        self.raw_squares += np.sum(rows[:, :self.p] ** 2, axis=0)
        if not block.has_level:
            self.free = _stack_qr(self.free, rows)
            return
        rows = np.column_stack([sw, rows])
        fresh: dict[int, list[tuple[int, int]]] = {}   # length -> (trajectory, start)
        for j, start, stop in runs(block.group):
            w = block.weight[start:stop]
            self.total_weight[j] += w.sum()
            self.weighted_A[j] += w @ block.A[start:stop]
            self.weighted_b[j] += w @ block.b[start:stop]
            if self.level[j] is None:
                fresh.setdefault(stop - start, []).append((j, start))
            else:
                self.level[j] = _stack_qr(self.level[j], rows[start:stop])
        # the first rows of trajectories of one length in one call: a call each took
        # most of the time of 5,000 short trajectories
        for length, first in fresh.items():
            starts = np.array([start for _, start in first])
            factors = np.linalg.qr(rows[starts[:, None] + np.arange(length)], mode="r")
            for (j, _), R in zip(first, factors, strict=True):
                self.level[j] = R

    def scaled(self, scale: float) -> Factor:
        """The factor of the same rows with every weight multiplied by `scale`."""
        root = np.sqrt(scale)
        copy = Factor(self.p, len(self.level))
        copy.level = [None if R is None else root * R for R in self.level]
        copy.free = None if self.free is None else root * self.free
        copy.weighted_A, copy.weighted_b = scale * self.weighted_A, scale * self.weighted_b
        copy.total_weight = scale * self.total_weight
        copy.raw_squares = scale * self.raw_squares
        copy.n_rows = self.n_rows
        return copy

    @staticmethod
    def joined(factors: Sequence[Factor]) -> Factor:
        """The factor of the rows of all `factors` (of as many trajectories) together."""
        first = factors[0]
        whole = Factor(first.p, len(first.level))
        for factor in factors:
            whole.level = [R if S is None else S if R is None else _stack_qr(R, S)
                           for R, S in zip(whole.level, factor.level, strict=True)]
            if factor.free is not None:
                whole.free = factor.free if whole.free is None else _stack_qr(whole.free,
                                                                              factor.free)
            whole.weighted_A = whole.weighted_A + factor.weighted_A
            whole.weighted_b = whole.weighted_b + factor.weighted_b
            whole.total_weight = whole.total_weight + factor.total_weight
            whole.raw_squares = whole.raw_squares + factor.raw_squares
            whole.n_rows += factor.n_rows
        return whole

    @property
    def level_means(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Weighted means of A and b in each trajectory (NaN for one without level rows)."""
        inverse = np.divide(1.0, self.total_weight, out=np.full(len(self.total_weight), np.nan),
                            where=self.total_weight > 0)
        return self.weighted_A * inverse[:, None], self.weighted_b * inverse

    def centred(self) -> npt.NDArray[np.float64]:
        """The factor R of all rows, centred [sqrt(w) A, sqrt(w) b], shape (p + 1, p + 1)."""
        pieces = [R[1:, 1:] for R in self.level if R is not None]
        if self.free is not None:
            pieces.append(self.free)
        return _stack_qr(None, np.vstack(pieces))


def _stack_qr(R: npt.NDArray[np.float64] | None,
              rows: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The triangular factor of an earlier factor stacked on new rows."""
    return np.linalg.qr(rows if R is None else np.vstack([R, rows]), mode="r")


@dataclass(frozen=True)
class Solution:
    """Parameters of the centred problem and the linear map from row errors to them.

    theta - theta_true = G.T @ e  for row errors e (unweighted), so every covariance
    estimator works from G and the residuals; G_i = w_i (a_i - mean_j a) @ inverse, with
    `inverse` that of the centred weighted normal matrix (`Centred.influence`).
    """

    theta: npt.NDArray[np.float64]
    inverse: npt.NDArray[np.float64]           # (p, p)
    singular_values: npt.NDArray[np.float64]   # of the column-scaled centred design


def solve(centred: Centred, names: Sequence[str], *, n_levels: int = 0) -> Solution:
    """Least squares of the centred rows; a FitError names undetermined parameters.

    The triangular factor of [A, b] is that of its pieces stacked (tall-skinny QR)."""
    R = None
    for A, b, _ in centred.pieces():
        R = _stack_qr(R, np.column_stack([A, b]))
    assert R is not None
    return solve_factor(R, centred.raw_norms, centred.n_rows, names, n_levels=n_levels)


def solve_factor(R: npt.NDArray[np.float64], raw_norms: npt.NDArray[np.float64], n_rows: int,
                 names: Sequence[str], *, n_levels: int = 0) -> Solution:
    """Least squares from the triangular factor R of the centred rows [A, b].

    The SVD of the column-scaled factor is that of the column-scaled design, so rank and
    conditioning are judged exactly as on all rows.
    """
    p = len(names)
    if n_rows <= p + n_levels:
        raise FitError(f"cannot determine {', '.join(names)}: {n_rows} rows for {p + n_levels} "
                       f"unknowns ({p} parameters"
                       + (f" and {n_levels} energy level{'s' if n_levels > 1 else ''})"
                          if n_levels else ")")
                       + ", which leaves nothing to estimate their errors from")
    A, b = R[:, :p], R[:, p]
    scale = np.linalg.norm(A, axis=0)
    varies = scale > _VARIES * raw_norms
    still = [name for name, v in zip(names, varies, strict=True) if not v]
    if still:
        subject, pronoun = ("its term does", "it") if len(still) == 1 else (
            "their terms do", "them")
        raise FitError(f"cannot determine {', '.join(still)}: {subject} not vary along any "
                       f"trajectory, so the energy level absorbs {pronoun}")
    U, s, Vt = np.linalg.svd(A / scale, full_matrices=False)
    tolerance = _RANK_TOLERANCE * s[0]
    if s[-1] <= tolerance or not np.all(np.isfinite(s)):
        _raise_rank_deficient(s, Vt, names, tolerance)
    theta = (Vt.T @ ((U.T @ b) / s)) / scale
    inverse = (Vt.T / s**2) @ Vt / np.outer(scale, scale)
    return Solution(theta, inverse, s)


def solve_adjusted(pieces: Iterable[tuple[npt.NDArray[np.float64], ...]],
                   AA: npt.NDArray[np.float64], Ab: npt.NDArray[np.float64],
                   names: Sequence[str]) -> Solution:
    """Adjusted least squares: the corrected moment equations (A'WA + AA) theta = A'Wb + Ab.

    The adjusted estimator is defined by corrected sums of products, so it cannot work
    on the design matrix alone as `solve` does; the equations are scaled to unit diagonal
    and solved through their eigendecomposition, which also shows when the correction
    leaves them indefinite (noise too large for the data).
    """
    gram, moment = AA.copy(), Ab.copy()
    for A, b, _ in pieces:   # the centred weighted rows (`Centred.pieces`)
        gram += A.T @ A
        moment += A.T @ b
    diagonal = np.diag(gram)
    if not np.all(diagonal > 0):
        bad = [n for n, d in zip(names, diagonal, strict=True) if not d > 0]
        raise FitError(f"cannot correct the noise bias of {', '.join(bad)}: the noise "
                       "given is as large as their terms' variation")
    scale = np.sqrt(diagonal)
    eigenvalues, V = np.linalg.eigh(gram / np.outer(scale, scale))
    if eigenvalues[0] <= _RANK_TOLERANCE * eigenvalues[-1]:
        weight = np.abs(V[:, 0])
        involved = [n for n, w in zip(names, weight, strict=True) if w > 0.1]
        raise FitError(f"cannot correct the noise bias: after the correction the data no "
                       f"longer determine {', '.join(involved)} (the noise given is too large "
                       "for these data, or overstated)")
    inverse = (V / eigenvalues) @ V.T / np.outer(scale, scale)
    theta = inverse @ moment
    return Solution(theta, inverse, np.sqrt(eigenvalues[::-1]))


def _raise_rank_deficient(s: np.ndarray, Vt: np.ndarray, names: Sequence[str],
                          tolerance: float) -> None:
    null = Vt[s <= tolerance]
    weight = np.sqrt(np.sum(null**2, axis=0))
    involved = [n for n, w in zip(names, weight, strict=True) if w > 1e-3]
    rank = int(np.sum(s > tolerance))
    raise FitError(f"cannot determine {', '.join(involved)}: their terms are collinear in "
                   f"these data (rank {rank} of {len(names)}); record larger or more varied "
                   "motion, fix one of them with --fix, or drop a term from the model")


@dataclass(frozen=True)
class Conditioning:
    """Conditioning of the column-scaled design with the energy-level columns included."""

    condition_number: float
    singular_values: tuple[float, ...]
    weakest_direction: dict[str, float]
    status: str


STATUS_LIMITS = (("ok", 30.0), ("moderate", 1000.0))


def conditioning(blocks: Sequence[Block], names: Sequence[str],
                 labels: Sequence[str | int]) -> Conditioning:
    """Singular values of [A, level columns], scaled to unit column norms."""
    factor = Factor(len(names), len(labels))
    for block in blocks:
        for start in range(0, block.n_rows, PIECE_ROWS):
            factor.add(block.slice(start, start + PIECE_ROWS))
    return factor_conditioning(factor, names, labels)


def factor_conditioning(factor: Factor, names: Sequence[str],
                        labels: Sequence[str | int]) -> Conditioning:
    """`conditioning` from the rows' triangular factors, in time linear in the trajectories.

    With every column scaled to unit norm, the level columns L are orthonormal (each lives
    on its own trajectory's rows), so the design is [A, L] = [Q_c, L] K with
    K = [[R_c, 0], [B, I]]: R_c the factor of A centred within each trajectory (and of
    the rows without a level), B = L^T A, and [Q_c, L] orthonormal. Rotating the level
    coordinates by the QR of B = Q_b R_b leaves [[R_c, 0], [R_b, I]] (at most 2p square)
    and an identity: the singular values are that block's and ones, and its singular
    vectors give the weakest direction, never a dense matrix of all J levels.
    """
    J, p = len(labels), len(names)
    has_level = np.array([k < len(factor.level) and factor.level[k] is not None
                          for k in range(J)], dtype=bool)
    W = factor.total_weight[:J][has_level]
    scale = np.sqrt(factor.raw_squares)
    R_c = factor.centred()[:p, :p] / scale
    B = factor.weighted_A[:J][has_level] / np.sqrt(W)[:, None] / scale
    Q_b, R_b = np.linalg.qr(B)
    k = R_b.shape[0]
    K = np.zeros((p + k, p + k))
    K[:R_c.shape[0], :p] = R_c
    K[p:, :p] = R_b
    K[p:, p:] = np.eye(k)
    if not np.all(np.isfinite(K)):   # a column zero over these rows: they do not determine it
        return Conditioning(float("inf"), (), {}, "severe")
    _, s_block, Vt = np.linalg.svd(K)
    ones = len(W) - k
    s = np.sort(np.concatenate([s_block, np.ones(ones)]))[::-1]
    condition = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    if ones and s_block[-1] > 1:   # the weakest: levels alone, a combination B does not see
        row = int(np.argmin(np.sum(Q_b**2, axis=1)))
        level = -Q_b @ Q_b[row]
        level[row] += 1.0
        weakest = np.concatenate([np.zeros(p), level / np.linalg.norm(level)])
    else:
        weakest = np.concatenate([Vt[-1, :p], Q_b @ Vt[-1, p:]])
    weakest *= np.sign(weakest[np.argmax(np.abs(weakest))])
    labelled = [*names, *(f"h[{label}]" for label, used in zip(labels, has_level,
                                                                strict=True) if used)]
    direction = {name: float(w) for name, w in zip(labelled, weakest, strict=True)
                 if name in names or abs(w) >= 0.05}
    status = next((label for label, limit in STATUS_LIMITS if condition < limit), "severe")
    return Conditioning(condition, tuple(float(x) for x in s), direction, status)
