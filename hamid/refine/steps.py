"""The trajectory fit's Gauss-Newton step (docs/method.md, "The trajectory refinement"):
the normal equations of its segments, the Marquardt-damped step they give, and the
damping's schedule.

The fit steps undamped while its steps lower the misfit. A step that makes it worse is
taken again from the best point, damped, and more so each time it fails again (the factor
times 2, 4, 8, ...). A step that lowers it sets the next damping by how well the step's
quadratic model foretold the drop: with the gain ratio rho = actual / predicted drop, the
factor is multiplied by max(1/3, 1 - (2 rho - 1)^3) (Nielsen's rule: K. Madsen, H. B.
Nielsen and O. Tingleff, *Methods for non-linear least squares problems*, 2nd ed., DTU
2004, section 3.2), so that a good model lets the damping go down by thirds and a poor
one raises it. Cutting it by ten after every good step instead (the rule before) made
a fit far from its minimum fail every other step: from the linear start of a damped
two-mass chain's accelerations integrated twice, steps damped at 0.01 dropped the misfit
as foretold and the next ones, at 0.001, raised it, for 50 iterations. Damped until the
drop it foretells is rounding (ROUNDING), a step hands over to the undamped one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["ROUNDING", "Damping", "Normal", "scores"]

FIRST = 1e-3     # the damping of the first step taken again
LEAST = 1e-6     # below it, the steps are undamped again
# Of the misfit: a rise below it is rounding (the step is not worse), and so is a drop a
# damped step foretells below it: the undamped step then judges whether the minimum is
# reached, and when it fails again from the same point, no step lowers the misfit
ROUNDING = 1e-12


@dataclass(frozen=True)
class Damping:
    """The damping factor of the next step (0: undamped) and its growth should it fail."""

    factor: float = 0.0
    growth: float = 2.0

    def failed(self) -> Damping:
        """The damping of the step taken again after one that made the misfit worse."""
        return Damping(max(self.growth * self.factor, FIRST), 2 * self.growth)

    def succeeded(self, drop: float, predicted: float) -> Damping:
        """The damping after a step that lowered the misfit by `drop`, its quadratic model
        having foretold `predicted`."""
        ratio = min(max(drop / predicted, 0.0), 1.0) if predicted > 0 else 1.0
        factor = self.factor * max(1 / 3, 1 - (2 * ratio - 1) ** 3)
        return Damping(factor if factor >= LEAST else 0.0)


@dataclass(frozen=True)
class Normal:
    """Gauss-Newton normal equations of every segment, or group of tied segments in its
    first state, the states not yet eliminated."""

    cost: npt.NDArray[np.float64]   # (S, 2N): weighted squared residuals of each variable
    H_tt: npt.NDArray[np.float64]   # (S, p, p)
    g_t: npt.NDArray[np.float64]    # (S, p)
    H_xx: npt.NDArray[np.float64]   # (S, 2N, 2N)
    H_xt: npt.NDArray[np.float64]   # (S, 2N, p)
    g_x: npt.NDArray[np.float64]    # (S, 2N)
    # (S,): what closing a group's gaps adds to its cost, to first order in the residuals
    closing: npt.NDArray[np.float64] | float = 0.0

    @property
    def misfit(self) -> npt.NDArray[np.float64]:
        """Each segment's or group's weighted misfit, its gaps closed."""
        return self.cost.sum(axis=1) + self.closing

    @property
    def total(self) -> float:
        return float(self.cost.sum() + np.sum(self.closing))

    def step(self, damping: float) -> tuple[Any, Any, Any, float]:
        """Parameter step, segment-state steps, the Schur complement (Marquardt-damped) and
        the drop of the misfit the quadratic model foretells for the step, g.h + damping
        h.D.h (D the diagonal damped)."""
        n = self.H_xx.shape[1]
        H_tt, D_xx = self.H_tt.sum(axis=0), np.einsum("sii->si", self.H_xx)
        H_xx = self.H_xx + damping * D_xx[:, :, None] * np.eye(n)
        inverse = np.linalg.inv(H_xx)
        schur = (H_tt + damping * np.diag(np.diag(H_tt))
                 - np.einsum("sak,sab,sbl->kl", self.H_xt, inverse, self.H_xt))
        rhs = self.g_t.sum(axis=0) - np.einsum("sak,sab,sb->k", self.H_xt, inverse, self.g_x)
        d_theta = np.linalg.solve(schur, rhs)
        d_x = np.einsum("sab,sb->sa", inverse,
                        self.g_x - np.einsum("sak,k->sa", self.H_xt, d_theta))
        predicted = (self.g_t.sum(axis=0) @ d_theta + np.sum(self.g_x * d_x) + damping * (
            np.diag(H_tt) @ d_theta**2 + np.sum(D_xx * d_x**2)))
        return d_theta, d_x, schur, float(predicted)


def scores(normal: Normal) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Each group's score (G, p) and Schur complement (G, p, p), its state eliminated."""
    inverse = np.linalg.inv(normal.H_xx)
    return (normal.g_t - np.einsum("sak,sab,sb->sk", normal.H_xt, inverse, normal.g_x),
            normal.H_tt - np.einsum("sak,sab,sbl->skl", normal.H_xt, inverse, normal.H_xt))
