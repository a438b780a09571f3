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

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.design import Block, Windows
from hamid.errors import UsageError
from hamid.expr import Polynomial
from hamid.model import Model
from hamid.records import Records

__all__ = ["Moments", "adjusted_moments", "unbiased"]


def _hermite_table(y: npt.NDArray[np.float64], sigma: float, top: int) -> list[Any]:
    """s^n He_n(y/s) for n = 0..top: H_0 = 1, H_1 = y, H_n+1 = y H_n - n s^2 H_n-1."""
    table: list[Any] = [np.ones_like(y), y]
    for n in range(1, top):
        table.append(y * table[n] - n * sigma**2 * table[n - 1])
    return table[:top + 1]


def unbiased(poly: Polynomial, Y: npt.NDArray[np.float64],
             sigma: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Unbiased estimate of poly(x) from y = x + Gaussian noise of std sigma (per variable)."""
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


def check_adjustable(model: Model, derived_velocities: bool, damping: Any) -> None:
    """The adjustment needs polynomial terms that are functions of one sample each."""
    if not model.is_polynomial:
        raise UsageError("--bias-correct needs a polynomial energy; for this model hamid "
                         "does not correct the noise bias (it may be small at low noise)")
    if derived_velocities:
        raise UsageError("--bias-correct needs measured velocities: derived velocities mix "
                         "the noise of neighbouring samples")
    if damping.kinds:
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
    held = [(model.parameters.index(name), value) for name, value in fixed.items()]

    def known(base: Any, parts: Sequence[Any]) -> Polynomial:
        """-(base + sum of the fixed parameters' terms), the known side of the rows."""
        funcs = [base, *(parts[k] for k, _ in held)]
        return _negate(Polynomial.combine(funcs, [1.0, *(v for _, v in held)]))

    if block.kind == "energy":
        functions = [[model.phi[k] for k in index]]
        target = [known(model.E0, model.phi)]
        operators = [None if windows is None else windows.means]
        coordinates = [None]
    else:
        assert windows is not None
        lag = model.lagrangian
        parts = (lag.L0, *lag.L)
        coordinates = list(range(len(model.coordinates)))
        functions, target, operators = [], [], [windows.Q_dpsi, windows.Q_psi]
        for i in coordinates:
            dv = [f.diff(model.velocities[i]) for f in parts]
            dq = [f.diff(model.coordinates[i]) for f in parts]
            functions.append(([dv[k + 1] for k in index], [dq[k + 1] for k in index]))
            target.append((known(dv[0], dv[1:]), known(dq[0], dq[1:])))
    if block.kind == "energy":
        return _energy_moments(block, functions[0], target[0], operators[0], Y, sigma,
                               records.group)
    return _weak_moments(block, functions, target, operators, Y, sigma)


def _negate(f: Any) -> Polynomial:
    return Polynomial(f.variables, f.exponents, -f.coefficients)


def _at(functions: Sequence[Polynomial], target: Polynomial, theta: Any) -> Polynomial:
    """sum_k theta_k functions_k - target: what the rows equate to zero, at theta."""
    return Polynomial.combine([*functions, target], [*theta, -1.0])


def _pairs_at(functions: Sequence[Polynomial], g: Polynomial, Y: np.ndarray,
              sigma: np.ndarray) -> np.ndarray:
    """(n_samples, p): the self-pair bias of each function with g, at every sample."""
    return np.column_stack([_self_pair(f, g, Y, sigma) for f in functions]) if functions \
        else np.zeros((len(Y), 0))


def _energy_moments(block: Block, phi: list[Polynomial], minus_E0: Polynomial,
                    P: Any, Y: np.ndarray, sigma: np.ndarray,
                    sample_group: np.ndarray) -> Moments:
    """Energy rows (per sample, or window means P), centred within each trajectory."""
    import dataclasses

    columns = np.column_stack([unbiased(f, Y, sigma) for f in phi]) if phi else \
        np.zeros((len(Y), 0))
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
    AA = np.array([[self_weight @ _self_pair(p, q, Y, sigma) for q in phi] for p in phi])
    Ab = np.array([self_weight @ _self_pair(p, minus_E0, Y, sigma) for p in phi])
    # The centring term -W_j shares_s^2 of each sample, shared by its trajectory's rows.
    centring = W[sample_group] * (w / W[block.group] if P is None else shares) ** 2
    own = w if P is None else P.multiply(P)

    def row_shares(theta: Any) -> Any:
        d = _pairs_at(phi, _at(phi, minus_E0, theta), Y, sigma)
        total = np.stack([np.bincount(sample_group, weights=centring * d[:, k],
                                      minlength=n_groups) for k in range(len(phi))], axis=1)
        mine = own[:, None] * d if P is None else w[:, None] * (own @ d)
        return mine - (w / W[block.group])[:, None] * total[block.group]

    return Moments(dataclasses.replace(block, A=A, b=b), AA.reshape(len(phi), len(phi)), Ab,
                   row_shares)


def _weak_moments(block: Block, functions: list[Any], target: list[Any], operators: list[Any],
                  Y: np.ndarray, sigma: np.ndarray) -> Moments:
    """Weak rows (window, coordinate) = sum over operators (psi', psi) of Q f(y)."""
    import dataclasses

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

    def row_shares(theta: Any) -> Any:
        out = np.zeros((n_windows * N, p))
        for i, (per_operator, per_target) in enumerate(zip(functions, target, strict=True)):
            w = block.weight[i::N]
            for Qa, fa in zip(operators, per_operator, strict=True):
                for Qc, fc, tc in zip(operators, per_operator, per_target, strict=True):
                    d = _pairs_at(fa, _at(fc, tc, theta), Y, sigma)
                    out[i::N] += w[:, None] * (Qa.multiply(Qc) @ d)
        return out

    return Moments(dataclasses.replace(block, A=A, b=b), AA, Ab, row_shares)
