"""What the noise of the recorded inputs does to a driven trajectory fit, without drawing it.

The refinement integrates the recorded inputs u on a cubic spline (not-a-knot) through
their samples (`hamid.refine.integration.SampledInputs`), so a change du of the samples
moves the integrated state, to first order, by

    dx(t) = Phi(t) int_0^t q(s) du(s) ds,   q = Phi^-1 B,

Phi(t) = dx(t)/dx0 the state transition from the segment's start (its Jacobian's copies
of the initial state already carry it), B = df/du the inputs' effect on the equations'
rates and du(s) the spline through the changed samples. The residuals at later samples
move by their Jacobian J_x (by the initial state) times that integral, so the change of
the segment's scores J'W^2 r and of its end state are

    dg = -int_0^T Lambda(s) q(s) du(s) ds,   Lambda(s) = sum over samples t_i > s of J_i'W^2 J_x,i
    dend = Phi(end) int_0^end q(s) du(s) ds

(Lambda is constant between samples). Both are exact integrals of smooth functions times
a cubic: q is interpolated by a cubic spline of its values at the integration's output
times and each interval taken by four-point Gauss-Legendre (exact for the product of two
cubics), and the spline's dependence on its samples is applied transposed
(`spline_gradient`), so a whole segment's response to every sample of every input comes
out of one pass over it: the Jacobian's copies, no copy more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.interpolate import make_interp_spline
from scipy.linalg import solve_banded

__all__ = ["Segment", "spline_gradient", "response"]

Array = npt.NDArray[np.float64]

GAUSS_NODES, GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(4)


def spline_gradient(x: Array, points: Array, z: Array) -> Array:
    """The gradient by the values y at the knots `x` (n >= 4) of sum_p z_p s(points_p),
    s the not-a-knot cubic spline through (x, y) as scipy's CubicSpline makes it; `z` is
    (P, F), one functional per column: the result is (n, F)."""
    n = len(x)
    h = np.diff(x)
    k = np.clip(np.searchsorted(x, points, side="right") - 1, 0, n - 2)
    basis = _hermite(((points - x[k]) / h[k])[:, None])
    by_value = _summed(k, basis[0] * z, n) + _summed(k + 1, basis[2] * z, n)
    by_slope = (_summed(k, h[k, None] * basis[1] * z, n)
                + _summed(k + 1, h[k, None] * basis[3] * z, n))
    return _through_slopes(x, by_value, by_slope)


def _hermite(t: Array) -> tuple[Array, Array, Array, Array]:
    """Hermite's cubic basis at t in [0, 1] of an interval: the weights of its start's
    value, start's slope (times the width), end's value and end's slope (times the width)."""
    t2, t3 = t * t, t * t * t
    return 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + t, 3 * t2 - 2 * t3, t3 - t2


def _through_slopes(x: Array, by_value: Array, by_slope: Array) -> Array:
    """The gradient by the knots' values of a functional of a not-a-knot spline through
    them, from its gradient by each knot's value and slope as Hermite's form has them:
    the slopes solve scipy's banded system A s = C y, so their part is C' A'^-1 by_slope,
    one banded solve for all columns."""
    n = len(x)
    h = np.diff(x)
    grad = by_value.copy()
    # A transposed, in solve_banded's layout: its upper band is A's lower one and back
    diagonal = np.empty(n)
    upper, lower = np.zeros(n), np.zeros(n)   # A[i, i + 1] at i + 1, A[i + 1, i] at i
    diagonal[1:-1] = 2 * (h[:-1] + h[1:])
    upper[2:], lower[:-2] = h[:-1], h[1:]
    start, end = x[2] - x[0], x[-1] - x[-3]
    diagonal[0], upper[1] = h[1], start
    diagonal[-1], lower[-2] = h[-2], end
    transposed = np.array([np.r_[0.0, lower[:-1]], diagonal, np.r_[upper[1:], 0.0]])
    lam = solve_banded((1, 1), transposed, by_slope, check_finite=False)
    # C' lam: the right-hand side's dependence on the secants (y[i + 1] - y[i]) / h[i]
    by_secant = np.zeros((n - 1, by_value.shape[1]))
    by_secant[:-1] += 3 * h[1:, None] * lam[1:-1]
    by_secant[1:] += 3 * h[:-1, None] * lam[1:-1]
    by_secant[0] += (h[0] + 2 * start) * h[1] / start * lam[0]
    by_secant[1] += h[0] ** 2 / start * lam[0]
    by_secant[-2] += h[-1] ** 2 / end * lam[-1]
    by_secant[-1] += (2 * end + h[-1]) * h[-2] / end * lam[-1]
    by_secant /= h[:, None]
    grad[:-1] -= by_secant
    grad[1:] += by_secant
    return grad


def _summed(index: npt.NDArray[np.intp], values: Array, n: int) -> Array:
    """The rows of `values` summed by `index` into n rows (np.add.at, faster)."""
    order = np.argsort(index, kind="stable")
    unique, first = np.unique(index[order], return_index=True)
    out = np.zeros((n, values.shape[1]))
    out[unique] = np.add.reduceat(values[order], first, axis=0)
    return out


def _solved(A: Array, B: Array) -> Array:
    """A^-1 B for matrices on the last two axes; 2 x 2 ones (one degree of freedom) by
    Cramer's rule: 0.3 against 2.3 ms for 15 x 1251 of them by numpy's solve."""
    if A.shape[-1] != 2:
        return np.linalg.solve(A, B)
    a, b, c, d = (A[..., i, j, None] for i in (0, 1) for j in (0, 1))
    det = a * d - b * c
    out = np.empty(np.broadcast_shapes(A.shape[:-1], B.shape[:-2] + (2,)) + B.shape[-1:])
    out[..., 0, :] = (d * B[..., 0, :] - b * B[..., 1, :]) / det
    out[..., 1, :] = (a * B[..., 1, :] - c * B[..., 0, :]) / det
    return out


HERMITE_AT_GAUSS = np.array(_hermite((1 + GAUSS_NODES) / 2)).T   # (Gauss point, basis)


@dataclass(frozen=True)
class Segment:
    """Segments integrated alike (the same output times and samples), as `response` needs
    them, S of them on each array's first axis.

    `times` (G,) are the integration's output times through the segments' end, `phi`
    (S, G, 2N, 2N) the state transition and `B` (S, G, 2N, n_inputs) the rates'
    derivatives by the inputs there; `samples` (m,) index the samples into `times` and
    `products` (S, m, c, 2N) are each sample's J_i'W^2 J_x,i (c the Jacobian's columns);
    `direct` (S, m, c, n_inputs), when accelerations are recorded, what an input's value
    at a sample moves its scores by directly (-J_i'W^2 da/du). The end is the last time."""

    times: Array
    phi: Array
    B: Array
    samples: npt.NDArray[np.intp]
    products: Array
    direct: Array | None = None


def response(segment: Segment, knots: Array, outputs: Array) -> Array:
    """The change of chosen combinations of each segment's scores and end state by each
    value of the inputs' spline at its `knots` (which hold the segments' sample times and
    end), (S, len(knots), r, n_inputs), to first order (module docstring); `outputs`
    (S, r, c + 2N) are the combinations (the refinement wants the parameters' move, r of
    them where the scores and end state are c + 2N: combined first, the rest is smaller)."""
    times, phi = segment.times, segment.phi
    S, _, n_states, n_inputs = segment.B.shape
    c, K, n_gauss = segment.products.shape[2], len(knots), len(GAUSS_NODES)
    r = outputs.shape[1]
    by_scores, by_end = outputs[..., :c], outputs[..., c:]
    q = _solved(phi, segment.B)                             # (S, G, 2N, n_inputs)
    last = int(np.argmin(np.abs(knots - times[-1])))        # the end's knot
    left, width = knots[:last], np.diff(knots[:last + 1])
    points = (left[:, None] + width[:, None] * (1 + GAUSS_NODES) / 2).ravel()
    # not-a-knot, as CubicSpline makes it; its B-spline form builds three times faster
    q_points = make_interp_spline(times, q, k=3, axis=1)(points)   # (S, P, 2N, n_inputs)
    # Lambda on each knot interval, combined: the samples after it, each at its own knot
    nearest = np.searchsorted(knots, times[segment.samples] - 0.5 * np.min(width))
    at_knot = np.zeros((S, K + 1, r, n_states))
    at_knot[:, nearest] = by_scores[:, None] @ segment.products
    after = np.cumsum(at_knot[:, ::-1], axis=1)[:, ::-1]    # sum over knots >= j
    # what q moves the outputs by on each interval: -Lambda for the scores, Phi(end) for
    # the end state; times each interval's integral of q and each of Hermite's basis
    # functions, whose weights are its knots' values and slopes
    by_q = (by_end @ phi[:, -1])[:, None] - after[:, 1:last + 1]     # (S, last, r, 2N)
    rule = (width[:, None] * GAUSS_WEIGHTS / 2)[..., None] * HERMITE_AT_GAUSS   # (last, 4, 4)
    by_basis = (q_points.reshape(S, last, n_gauss, -1).swapaxes(2, 3) @ rule).reshape(
        S, last, n_states, n_inputs * 4)
    F = r * n_inputs
    at_ends = (by_q @ by_basis).reshape(S, last, F, 4)
    by_value, by_slope = np.zeros((2, K, S, F))
    by_value[:last] += at_ends[..., 0].swapaxes(0, 1)
    by_value[1:last + 1] += at_ends[..., 2].swapaxes(0, 1)
    by_slope[:last] += width[:, None, None] * at_ends[..., 1].swapaxes(0, 1)
    by_slope[1:last + 1] += width[:, None, None] * at_ends[..., 3].swapaxes(0, 1)
    if segment.direct is not None:   # the acceleration residuals at the samples themselves
        by_value[nearest] += (by_scores[:, None] @ segment.direct).reshape(
            S, len(nearest), -1).swapaxes(0, 1)
    return _through_slopes(knots, by_value.reshape(K, -1), by_slope.reshape(K, -1)).reshape(
        K, S, r, n_inputs).swapaxes(0, 1)
