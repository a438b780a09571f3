"""Adjusted least squares: least-squares moments with the bias of measurement noise removed.

Noise in the measured states biases plain least squares, because the columns are powers
and products of noisy numbers: E[(x + e)^2] = x^2 + s^2. For polynomial energies the bias
is removed exactly in expectation under Gaussian noise (the adjusted least-squares
estimator of polynomial errors-in-variables models, Kukush, Schneeweiss and co-workers):
every monomial of the measured y is replaced by its unbiased estimate

    x^n  ->  s^n He_n(y / s)      (He_n the probabilists' Hermite polynomial),

products of independent channels multiply, and in the sums of squares and cross products
the terms that pair a sample with itself get the unbiased estimate of the product.

Every row of hamid's design is a linear functional of functions of the samples,

    A_rk = sum_s sum_a Q^a_rs f^a_k(y_s)          (a: one or two operators per block)

so the weighted Gram matrix A'WA is estimated without bias by

    A_H'WA_H + sum_s sum_ab c^ab_s (H[f^a_k f^b_l] - H[f^a_k] H[f^b_l])(y_s),
    c^ab_s = sum_r w_r Q^a_rs Q^b_rs,

with A_H the columns built from H[f]; the same holds for A'Wb.

The estimate solves sum_r psi_r(theta) = 0 with the corrected score of each row

    psi_r = w_r a_r (a_r theta - b_r) + (C_r theta - c_r),

C_r and c_r its part of the self-pair corrections (`Moments.shares`); psi_r has mean zero
at the true parameters, row by row, so the covariance is the sandwich of these scores
(the corrected-score estimator of Carroll, Ruppert, Stefanski and Crainiceanu,
"Measurement Error in Nonlinear Models", 2006, ch. 7). Scores of the residuals alone
carry the self-pair bias as a mean, which the sandwich counts as variance.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.data.records import Records
from hamid.errors import UsageError
from hamid.linear import solve
from hamid.linear.design import Block, RowKind, Windows
from hamid.model.expressions import Polynomial
from hamid.model.models import Model

__all__ = ["Moments", "adjusted_energy", "adjusted_moments", "unbiased"]


class _Hermite:
    """Unbiased estimates of polynomials of the states y, each kept once made, since the
    sums of products ask for the same ones often.

    The tables of s^n He_n(y/s) of each variable (H_0 = 1, H_1 = y,
    H_n+1 = y H_n - n s^2 H_n-1), a column per power, are made `solve.PIECE_ROWS` samples
    at a time and dropped: held whole, those of a product of cubics took 28 columns of
    the record (a joint fit's noise check peaked at 15 times its decoded data).
    """

    def __init__(self, Y: npt.NDArray[np.float64], sigma: npt.NDArray[np.float64]) -> None:
        self.Y, self.sigma = Y, sigma
        self.known: dict[Polynomial, npt.NDArray[np.float64]] = {}

    def of(self, poly: Polynomial) -> npt.NDArray[np.float64]:
        """The unbiased estimate of poly(x) at every sample."""
        if poly not in self.known:
            self.known[poly] = self.made(poly)
        return self.known[poly]

    def made(self, poly: Polynomial) -> npt.NDArray[np.float64]:
        """The unbiased estimate of poly(x) at every sample, not kept."""
        out = np.zeros(len(self.Y))
        if not len(poly.coefficients):
            return out
        highest = poly.exponents.max(axis=0)
        for start in range(0, len(self.Y), solve.PIECE_ROWS):
            Y = self.Y[start:start + solve.PIECE_ROWS]
            tables = [_hermite_table(Y[:, j], float(self.sigma[j]), int(top))
                      for j, top in enumerate(highest)]
            part = out[start:start + solve.PIECE_ROWS]
            for coefficient, row in zip(poly.coefficients, poly.exponents, strict=True):
                term = np.full(len(Y), coefficient)
                for j in np.flatnonzero(row):
                    term = term * tables[j][row[j]]
                part += term
        return out

    def columns(self, polys: Sequence[Polynomial]) -> npt.NDArray[np.float64]:
        """The estimates of `polys` as the columns of one array, each kept as a view of
        it (not a second copy)."""
        out = np.empty((len(self.Y), len(polys)), order="F")
        for k, poly in enumerate(polys):
            out[:, k] = self.known[poly] if poly in self.known else self.made(poly)
            self.known[poly] = out[:, k]
        return out

    def release(self) -> None:
        """Forget the estimates (each as large as the record), until asked again."""
        self.known.clear()

    def self_pair(self, p: Polynomial, q: Polynomial) -> npt.NDArray[np.float64]:
        """H[pq] - H[p] H[q] at every sample: the bias of pairing a sample with itself."""
        return self.made(_product(p, q)) - self.of(p) * self.of(q)


def _hermite_table(y: npt.NDArray[np.float64], sigma: float, top: int) -> list[Any]:
    """s^n He_n(y/s) for n = 0..top."""
    table: list[Any] = [np.ones_like(y), y]
    for n in range(1, top):
        table.append(y * table[n] - n * sigma**2 * table[n - 1])
    return table[:top + 1]


def unbiased(poly: Polynomial, Y: npt.NDArray[np.float64],
             sigma: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Unbiased estimate of poly(x) from y = x + Gaussian noise of std sigma (per variable)."""
    return _Hermite(Y, sigma).made(poly)


def _product(p: Polynomial, q: Polynomial) -> Polynomial:
    """The product of two polynomials in the same variables."""
    terms: dict[tuple[int, ...], float] = {}
    for ep, cp in zip(p.exponents, p.coefficients, strict=True):
        for eq, cq in zip(q.exponents, q.coefficients, strict=True):
            key = tuple(int(a + b) for a, b in zip(ep, eq, strict=True))
            terms[key] = terms.get(key, 0.0) + cp * cq
    return Polynomial.from_terms({k: c for k, c in terms.items() if c != 0.0}, p.variables)


@dataclass(frozen=True)
class Moments:
    """A block with unbiased columns, and the corrections of its sums of products.

    block : the block, its rows A, b built from unbiased estimates of every function.
    AA, Ab : the self-pair corrections of A'WA (p, p) and A'Wb (p,).
    shares : theta -> (n_rows, p), each row's part C_r theta - c_r of AA theta - Ab
        (a trajectory's centring shared by its rows in proportion to their weights);
        the rows' parts sum to AA theta - Ab.
    """

    block: Block
    AA: npt.NDArray[np.float64]
    Ab: npt.NDArray[np.float64]
    shares: Callable[[npt.NDArray[np.float64]], npt.NDArray[np.float64]]


def check_adjustable(model: Model, reconstructed: bool, damping: Any) -> None:
    """The adjustment needs polynomial terms that are functions of one sample each."""
    if not model.is_polynomial:
        raise UsageError("--bias-correct needs a polynomial energy; for this model hamid "
                         "does not correct the noise bias (it may be small at low noise)")
    if reconstructed:
        raise UsageError("--bias-correct needs measured velocities and positions: derived "
                         "or integrated ones mix the noise of neighbouring samples")
    if damping:
        raise UsageError("--bias-correct does not yet handle --damping (the dissipated work "
                         "mixes the noise of many samples)")


def adjusted_moments(block: Block, model: Model, records: Records, sigma: np.ndarray,
                     windows: Windows | None, parameters: Sequence[str],
                     fixed: dict[str, float]) -> Moments:
    """Unbiased columns and self-pair corrections of one block (energy or weak rows).

    `parameters` are the model parameters of the block's columns, in order; `fixed` the
    ones held at known values (their terms join the known side). The block's weights are
    taken as given.
    """
    index = [model.parameters.index(p) for p in parameters]
    known = _known_side(model, fixed)
    if block.kind == RowKind.ENERGY:
        phi, minus_E0 = _energy_functions(model, parameters, fixed)
        return _energy_moments(block, phi, minus_E0, windows, records, sigma)
    assert windows is not None
    lag = model.lagrangian
    parts = (lag.L0, *lag.L)
    functions, target = [], []
    for i in range(len(model.coordinates)):
        dv = [f.diff(model.velocities[i]) for f in parts]
        dq = [f.diff(model.coordinates[i]) for f in parts]
        functions.append(([dv[k + 1] for k in index], [dq[k + 1] for k in index]))
        target.append((known(dv[0], dv[1:]), known(dq[0], dq[1:])))
    return _weak_moments(block, functions, target, windows, records, sigma)


def adjusted_energy(block: Block, model: Model, records: Records, sigma: np.ndarray,
                    parameters: Sequence[str], fixed: dict[str, float]) -> solve.Solution:
    """The adjusted least-squares solution of energy rows of single samples, in memory
    that does not grow with the record: the unbiased columns are made a piece of samples
    at a time, twice (for each trajectory's means, then for the centred sums of
    products), never held whole as `adjusted_moments` holds them. The same solution as
    `adjusted_moments` then `hamid.linear.solve.solve_adjusted` (the same arithmetic on records
    of one piece); a FitError when the correction leaves it undetermined.
    """
    Y, w, group = records.X, block.weight, block.group
    phi, minus_E0 = _energy_functions(model, parameters, fixed)
    J = records.n_trajectories
    W = np.bincount(group, weights=w, minlength=J)
    AA, Ab = _corrections(phi, minus_E0, Y, sigma, w * (1 - w / W[group]))

    def rows(start: int) -> Block:
        piece = slice(start, start + solve.PIECE_ROWS)
        A = np.empty((len(Y[piece]), len(phi)))
        for k, f in enumerate(phi):
            A[:, k] = unbiased(f, Y[piece], sigma)
        return dataclasses.replace(block.slice(start, start + solve.PIECE_ROWS), A=A,
                                   b=unbiased(minus_E0, Y[piece], sigma))

    starts = range(0, len(Y), solve.PIECE_ROWS)
    sums_A, sums_b = np.zeros((J, len(phi))), np.zeros(J)
    for start in starts:
        piece = rows(start)
        sums_b += np.bincount(piece.group, weights=piece.weight * piece.b, minlength=J)
        for k in range(len(phi)):
            sums_A[:, k] += np.bincount(piece.group, weights=piece.weight * piece.A[:, k],
                                        minlength=J)
    inverse = np.divide(1.0, W, out=np.full(J, np.nan), where=W > 0)
    means = (sums_A * inverse[:, None], sums_b * inverse)
    pieces = ([solve.centred_piece(piece, means)] if len(starts) == 1   # as made above
              else (solve.centred_piece(rows(start), means) for start in starts))
    return solve.solve_adjusted(pieces, AA, Ab, list(parameters))


def _known_side(model: Model, fixed: dict[str, float]) -> Any:
    """Helper: known(base, parts) = -(base + the fixed parameters' terms among `parts`),
    the known side of rows built from `base` and every parameter's term `parts`."""
    held = [(model.parameters.index(name), value) for name, value in fixed.items()]

    def known(base: Any, parts: Sequence[Any]) -> Polynomial:
        funcs = [base, *(parts[k] for k, _ in held)]
        f = Polynomial.combine(funcs, [1.0, *(v for _, v in held)])
        return Polynomial(f.variables, f.exponents, -f.coefficients)

    return known


def _energy_functions(model: Model, parameters: Sequence[str],
                      fixed: dict[str, float]) -> tuple[list[Polynomial], Polynomial]:
    """Helper: the energy's terms of `parameters`, and minus its known part."""
    return ([model.phi[model.parameters.index(p)] for p in parameters],
            _known_side(model, fixed)(model.E0, model.phi))


def _corrections(phi: list[Polynomial], minus_E0: Polynomial, Y: np.ndarray,
                 sigma: np.ndarray, self_weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Helper: the self-pair corrections AA, Ab of energy rows, a piece of samples at a
    time, with each sample's weight in them (c_s)."""
    p = len(phi)
    upper = list(zip(*np.triu_indices(p), strict=True))
    pairs = [(phi[k], phi[m]) for k, m in upper] + [(f, minus_E0) for f in phi]
    sums = _block_pairs(_Hermite(Y, sigma), [self_weight], [pairs])[0]
    AA = np.zeros((p, p))
    for (k, m), value in zip(upper, sums, strict=False):
        AA[k, m] = AA[m, k] = value
    return AA, sums[len(upper):]


def _weighted_pairs(weight: np.ndarray, H: _Hermite,
                    pairs: Sequence[tuple[Polynomial, Polynomial]]) -> np.ndarray:
    """Helper: weight @ self_pair(f, g) for each pair. By einsum's own loop, not BLAS:
    many short products through BLAS each waited on its threads, which on a busy
    machine took half the time."""
    return np.array([np.einsum("i,i->", weight, H.self_pair(f, g)) for f, g in pairs])


def _block_pairs(H: _Hermite, weights: Sequence[np.ndarray],
                 pairs: Sequence[Sequence[tuple[Polynomial, Polynomial]]]) -> list[np.ndarray]:
    """Helper: `_weighted_pairs` of each weight with its pairs, over the samples of H a
    piece at a time (the biases of a block of windows' samples would be many columns of
    them)."""
    sums = [np.zeros(len(these)) for these in pairs]
    for start in range(0, len(H.Y), solve.PIECE_ROWS):
        rows = slice(start, start + solve.PIECE_ROWS)
        piece = _Hermite(H.Y[rows], H.sigma)
        for total, weight, these in zip(sums, weights, pairs, strict=True):
            total += _weighted_pairs(weight[rows], piece, these)
    return sums


def _at(functions: Sequence[Polynomial], target: Polynomial, theta: Any) -> Polynomial:
    """sum_k theta_k functions_k - target: what the rows equate to zero, at theta."""
    return Polynomial.combine([*functions, target], [*theta, -1.0])


def _pairs_at(functions: Sequence[Polynomial], g: Polynomial, H: _Hermite) -> np.ndarray:
    """(n_samples, p): the self-pair bias of each function with g, at every sample."""
    return np.column_stack([H.self_pair(f, g) for f in functions]) if functions \
        else np.zeros((len(H.Y), 0))


def _energy_parts(windows: Windows | None, n_samples: int) -> Iterator[tuple[slice, slice, Any]]:
    """Helper: energy rows a block at a time: the rows, the samples they are made of, and
    the operator from those samples to the rows (the windows' means, or None for rows of
    single samples, a piece of samples at a time)."""
    if windows is None:
        for start in range(0, n_samples, solve.PIECE_ROWS):
            piece = slice(start, min(start + solve.PIECE_ROWS, n_samples))
            yield piece, piece, None
        return
    for lo, hi, a, b in windows.blocks():
        yield slice(lo, hi), slice(a, b), windows.means_part(lo, hi, a, b)


def _energy_moments(block: Block, phi: list[Polynomial], minus_E0: Polynomial,
                    windows: Windows | None, records: Records, sigma: np.ndarray) -> Moments:
    """Energy rows (per sample, or the windows' means P), centred within each trajectory,
    made a block of rows at a time (`_energy_parts`)."""
    Y, sample_group, p = records.X, records.group, len(phi)
    w = block.weight
    n_groups = int(sample_group.max()) + 1  # every trajectory, with windows or not
    W = np.bincount(block.group, weights=w, minlength=n_groups)
    u = w / W[block.group]
    # c_s = sum_r w_r P_rs^2 - W_j (u'P)_s^2, u = w / W_j within the trajectory (P = I for
    # rows of single samples; every such trajectory has W > 0)
    A, b = np.empty((block.n_rows, p)), np.empty(block.n_rows)
    self_weight, centring = np.zeros(len(Y)), np.zeros(len(Y))
    for rows, samples, P in _energy_parts(windows, len(Y)):
        H = _Hermite(Y[samples], sigma)
        if P is None:
            A[rows], b[rows] = H.columns(phi), H.of(minus_E0)
            self_weight[samples], centring[samples] = w[rows], u[rows]
        else:
            A[rows], b[rows] = P @ H.columns(phi), P @ H.of(minus_E0)
            self_weight[samples] += P.multiply(P).T @ w[rows]
            centring[samples] += P.T @ u[rows]
    centring **= 2
    centring *= W[sample_group]
    self_weight -= centring
    AA, Ab = _corrections(phi, minus_E0, Y, sigma, self_weight)

    def row_shares(theta: Any) -> Any:
        """Each row's own self-pairs, less its weight's share of the centring term."""
        g = _at(phi, minus_E0, theta)
        total, mine = np.zeros((n_groups, p)), np.empty((block.n_rows, p))
        done = 0   # the samples before are in `total`: neighbouring blocks share some
        for rows, samples, P in _energy_parts(windows, len(Y)):
            d = _pairs_at(phi, g, _Hermite(Y[samples], sigma))
            new = slice(max(done, samples.start), samples.stop)
            for k in range(p):
                total[:, k] += np.bincount(sample_group[new], minlength=n_groups,
                                           weights=centring[new] * d[new.start
                                                                     - samples.start:, k])
            done = samples.stop
            mine[rows] = w[rows, None] * (d if P is None else P.multiply(P) @ d)
        return mine - u[:, None] * total[block.group]

    return Moments(dataclasses.replace(block, A=A, b=b), AA, Ab, row_shares)


def _weak_moments(block: Block, functions: list[Any], target: list[Any], windows: Windows,
                  records: Records, sigma: np.ndarray) -> Moments:
    """Weak rows (window, coordinate) = sum over operators (psi', psi) of Q f(y), made a
    block of windows at a time (`Windows.blocks`)."""
    N = len(functions)
    p = len(functions[0][0])
    A = np.zeros((windows.n_windows * N, p))
    b = np.zeros(windows.n_windows * N)
    AA, Ab = np.zeros((p, p)), np.zeros(p)
    for lo, hi, operators, H in _weak_parts(windows, records, sigma):
        for i, ((fv, fq), (tv, tq)) in enumerate(zip(functions, target, strict=True)):
            per_operator = [fv, fq]
            per_target = [tv, tq]
            rows = slice(lo * N + i, hi * N, N)
            for Q, fs, t in zip(operators, per_operator, per_target, strict=True):
                if p:
                    A[rows] += Q @ H.columns(fs)
                b[rows] += Q @ H.of(t)
            w = block.weight[rows]
            # per pair of operators (a, c): c^ac_s, which is c^ca_s, and the pairs of
            # functions whose self-pair biases it weighs: those of Ab, and of AA for
            # c >= a (the pairs (a, c) of AA are those of (c, a), transposed)
            terms, weights, pairs = [], [], []
            for a, (Qa, fa) in enumerate(zip(operators, per_operator, strict=True)):
                live = [k for k in range(p) if not fa[k].is_zero()]
                for c, (Qc, fc, tc) in enumerate(zip(operators, per_operator, per_target,
                                                     strict=True)):
                    both = [(k, m) for k in live for m in range(k if a == c else 0, p)
                            if c >= a and not fc[m].is_zero()]
                    terms.append((live, both, a != c))
                    weights.append(Qa.multiply(Qc).T @ w)
                    pairs.append([(fa[k], tc) for k in live]
                                 + [(fa[k], fc[m]) for k, m in both])
            values = _block_pairs(H, weights, pairs)
            for (live, both, mixed), value in zip(terms, values, strict=True):
                Ab[live] += value[:len(live)]
                for (k, m), v in zip(both, value[len(live):], strict=True):
                    AA[k, m] += v
                    if mixed or m != k:
                        AA[m, k] += v
            H.release()   # this coordinate's functions are not asked for again

    def row_shares(theta: Any) -> Any:
        out = np.zeros((windows.n_windows * N, p))
        for lo, hi, operators, H in _weak_parts(windows, records, sigma):
            for i, (per_operator, per_target) in enumerate(zip(functions, target,
                                                               strict=True)):
                rows = slice(lo * N + i, hi * N, N)
                w = block.weight[rows]
                for Qa, fa in zip(operators, per_operator, strict=True):
                    for Qc, fc, tc in zip(operators, per_operator, per_target, strict=True):
                        d = _pairs_at(fa, _at(fc, tc, theta), H)
                        out[rows] += w[:, None] * (Qa.multiply(Qc) @ d)
                H.release()
        return out

    return Moments(dataclasses.replace(block, A=A, b=b), AA, Ab, row_shares)


def _weak_parts(windows: Windows, records: Records,
                sigma: np.ndarray) -> Iterator[tuple[int, int, list[Any], _Hermite]]:
    """Helper: blocks of windows lo:hi, their operators (psi', psi) on the samples they
    cover, and those samples' unbiased estimates."""
    for lo, hi, a, b in windows.blocks():
        psi, dpsi = windows.operators(lo, hi)
        yield lo, hi, [dpsi, psi], _Hermite(records.X[a:b], sigma)
