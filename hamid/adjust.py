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
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid import solve
from hamid.design import Block, Windows
from hamid.errors import UsageError
from hamid.expr import Polynomial
from hamid.model import Model
from hamid.records import Records

__all__ = ["Moments", "adjusted_energy", "adjusted_moments", "unbiased"]


def _hermite_table(y: npt.NDArray[np.float64], sigma: float, top: int) -> list[Any]:
    """s^n He_n(y/s) for n = 0..top: H_0 = 1, H_1 = y, H_n+1 = y H_n - n s^2 H_n-1."""
    table: list[Any] = [np.ones_like(y), y]
    for n in range(1, top):
        table.append(y * table[n] - n * sigma**2 * table[n - 1])
    return table[:top + 1]


def unbiased(poly: Polynomial, Y: npt.NDArray[np.float64],
             sigma: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Unbiased estimate of poly(x) from y = x + Gaussian noise of std sigma (per variable).

    Its tables of Hermite polynomials are made for `solve.PIECE_ROWS` samples at a time
    (one per power of each variable: for a product of cubics, 28 columns of the samples)."""
    out = np.zeros(len(Y))
    for start in range(0, len(Y), solve.PIECE_ROWS):
        rows = slice(start, start + solve.PIECE_ROWS)
        out[rows] = _unbiased(poly, Y[rows], sigma)
    return out


def _unbiased(poly: Polynomial, Y: npt.NDArray[np.float64],
              sigma: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Helper: `unbiased` of one piece of samples."""
    out = np.zeros(len(Y))
    if not len(poly.coefficients):
        return out
    highest = poly.exponents.max(axis=0)
    tables = [_hermite_table(Y[:, j], float(sigma[j]), int(top))
              for j, top in enumerate(highest)]
    for coefficient, row in zip(poly.coefficients, poly.exponents, strict=True):
        term = np.full(len(Y), coefficient)
        for j in np.flatnonzero(row):
            term = term * tables[j][row[j]]
        out += term
    return out


def _product(p: Polynomial, q: Polynomial) -> Polynomial:
    """The product of two polynomials in the same variables."""
    terms: dict[tuple[int, ...], float] = {}
    for ep, cp in zip(p.exponents, p.coefficients, strict=True):
        for eq, cq in zip(q.exponents, q.coefficients, strict=True):
            key = tuple(int(a + b) for a, b in zip(ep, eq, strict=True))
            terms[key] = terms.get(key, 0.0) + cp * cq
    return Polynomial.from_terms({k: c for k, c in terms.items() if c != 0.0}, p.variables)


def _self_pair(p: Polynomial, q: Polynomial, Y: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """H[pq] - H[p] H[q] at every sample: the bias of pairing a sample with itself."""
    return unbiased(_product(p, q), Y, sigma) - unbiased(p, Y, sigma) * unbiased(q, Y, sigma)


@dataclass(frozen=True)
class Moments:
    """A block with unbiased columns, and the corrections of its sums of products.

    A, b : the block's rows built from unbiased estimates of every function.
    AA, Ab : the self-pair corrections of A'WA (p, p) and A'Wb (p,).
    """

    block: Block
    AA: npt.NDArray[np.float64]
    Ab: npt.NDArray[np.float64]


def check_adjustable(model: Model, derived_velocities: bool, damping: Any) -> None:
    """The adjustment needs polynomial terms that are functions of one sample each."""
    if not model.is_polynomial:
        raise UsageError("--bias-correct needs a polynomial energy; for this model hamid "
                         "does not correct the noise bias (it may be small at low noise)")
    if derived_velocities:
        raise UsageError("--bias-correct needs measured velocities: derived velocities mix "
                         "the noise of neighbouring samples")
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
    Y = records.X
    index = [model.parameters.index(p) for p in parameters]
    known = _known_side(model, fixed)
    if block.kind == "energy":
        phi, minus_E0 = _energy_functions(model, parameters, fixed)
        return _energy_moments(block, phi, minus_E0, None if windows is None
                               else windows.means, Y, sigma, records.group)
    assert windows is not None
    lag = model.lagrangian
    parts = (lag.L0, *lag.L)
    functions, target = [], []
    for i in range(len(model.coordinates)):
        dv = [f.diff(model.velocities[i]) for f in parts]
        dq = [f.diff(model.coordinates[i]) for f in parts]
        functions.append(([dv[k + 1] for k in index], [dq[k + 1] for k in index]))
        target.append((known(dv[0], dv[1:]), known(dq[0], dq[1:])))
    return _weak_moments(block, functions, target, [windows.Q_dpsi, windows.Q_psi], Y, sigma)


def adjusted_energy(block: Block, model: Model, records: Records, sigma: np.ndarray,
                    parameters: Sequence[str], fixed: dict[str, float]) -> solve.Solution:
    """The adjusted least-squares solution of energy rows of single samples, in memory
    that does not grow with the record: the unbiased columns are made a piece of samples
    at a time, twice (for each trajectory's means, then for the centred sums of
    products), never held whole as `adjusted_moments` holds them. The same solution as
    `adjusted_moments` then `hamid.solve.solve_adjusted` (the same arithmetic on records
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


def _energy_moments(block: Block, phi: list[Polynomial], minus_E0: Polynomial,
                    P: Any, Y: np.ndarray, sigma: np.ndarray,
                    sample_group: np.ndarray) -> Moments:
    """Energy rows (per sample, or window means P), centred within each trajectory."""
    columns = np.empty((len(Y), len(phi)))
    for k, f in enumerate(phi):   # a column at a time: no list of them stacked
        columns[:, k] = unbiased(f, Y, sigma)
    target = unbiased(minus_E0, Y, sigma)
    w = block.weight
    n_groups = int(sample_group.max()) + 1  # every trajectory, with windows or not
    W = np.bincount(block.group, weights=w, minlength=n_groups)
    if P is None:
        self_weight = w * (1 - w / W[block.group])  # W > 0: every sample is a row
        A, b = columns, target
    else:
        A, b = P @ columns, P @ target
        # c_s = sum_r w_r P_rs^2 - W_j (u'P)_s^2, u = w / W_j within the trajectory
        shares = P.T @ (w / W[block.group])
        self_weight = P.multiply(P).T @ w - W[sample_group] * shares**2
    return Moments(dataclasses.replace(block, A=A, b=b),
                   *_corrections(phi, minus_E0, Y, sigma, self_weight))


def _corrections(phi: list[Polynomial], minus_E0: Polynomial, Y: np.ndarray,
                 sigma: np.ndarray, self_weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Helper: the self-pair corrections AA, Ab of energy rows, a piece of samples at a
    time, with each sample's weight in them (c_s)."""
    AA, Ab = np.zeros((len(phi), len(phi))), np.zeros(len(phi))
    for start in range(0, len(Y), solve.PIECE_ROWS):
        rows = slice(start, start + solve.PIECE_ROWS)
        AA += [[self_weight[rows] @ _self_pair(p, q, Y[rows], sigma) for q in phi]
               for p in phi]
        Ab += [self_weight[rows] @ _self_pair(p, minus_E0, Y[rows], sigma) for p in phi]
    return AA, Ab


def _weak_moments(block: Block, functions: list[Any], target: list[Any], operators: list[Any],
                  Y: np.ndarray, sigma: np.ndarray) -> Moments:
    """Weak rows (window, coordinate) = sum over operators (psi', psi) of Q f(y)."""
    N = len(functions)
    p = len(functions[0][0])
    n_windows = operators[0].shape[0]
    A = np.zeros((n_windows * N, p))
    b = np.zeros(n_windows * N)
    AA, Ab = np.zeros((p, p)), np.zeros(p)
    for i, ((fv, fq), (tv, tq)) in enumerate(zip(functions, target, strict=True)):
        per_operator = [fv, fq]
        per_target = [tv, tq]
        for Q, fs, t in zip(operators, per_operator, per_target, strict=True):
            if p:
                A[i::N] += Q @ np.column_stack([unbiased(f, Y, sigma) for f in fs])
            b[i::N] += Q @ unbiased(t, Y, sigma)
        w = block.weight[i::N]
        for Qa, fa in zip(operators, per_operator, strict=True):
            for Qc, fc, tc in zip(operators, per_operator, per_target, strict=True):
                pair = Qa.multiply(Qc).T @ w  # c^ab_s
                for k in range(p):
                    Ab[k] += pair @ _self_pair(fa[k], tc, Y, sigma)
                    for m in range(p):
                        AA[k, m] += pair @ _self_pair(fa[k], fc[m], Y, sigma)
    return Moments(dataclasses.replace(block, A=A, b=b), AA, Ab)
