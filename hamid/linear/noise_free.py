"""Noise-free data: the misfit of a fit's rows, fed in pieces, and the widening of the
covariance it calls for when the residuals are the integrators' error rather than noise
(docs/method.md, "Covariances and intervals")."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from hamid.data.records import runs

if TYPE_CHECKING:
    from hamid.linear.design import Block

__all__ = ["CLEAN_RELATIVE", "Misfit", "at_least"]


# The energy rows' residual rms over their spread below which the data are noise-free.
# Clean simulated records sit at 1.3e-11 to 7e-11 (their integrator's error); noise of
# 1e-9 of each variable's spread, sixty times below the rounding of a float32 value
# (6e-8) and far below any sensor's, lifts them to 0.8-7e-9, and 1e-6 to 1e-6 and more
# (docs/method.md, "Covariances and intervals"; tests/benchmarks/clean_criterion.py).
CLEAN_RELATIVE = 1e-9


class Misfit:
    """The weighted squared residuals of a fit's rows, and its energy rows' residuals
    against their spread within each trajectory, fed a piece of rows at a time (a file
    read in chunks keeps no rows), the pieces of each trajectory in order."""

    def __init__(self, J: int) -> None:
        self.weighted = 0.0
        self.origin = np.full(J, np.nan)   # each trajectory's first b: sums are about it
        self.sums = np.zeros((J, 4))       # n, b, b^2, r^2 of the energy rows

    def add(self, block: Block, residual: npt.NDArray[np.float64],
            weight: npt.NDArray[np.float64]) -> None:
        """Rows of `block` with their (unweighted) residuals, weighted by `weight`."""
        self.weighted += float(weight @ residual**2)
        if not block.has_level:
            return
        for j, start, stop in runs(block.group):
            if np.isnan(self.origin[j]):
                self.origin[j] = block.b[start]
            b, r = block.b[start:stop] - self.origin[j], residual[start:stop]
            self.sums[j] += [len(b), b.sum(), b @ b, r @ r]

    @property
    def relative(self) -> float | None:
        """The energy rows' residual rms over the rms of their known side about its mean
        in each trajectory; None without energy rows."""
        n, b, bb, rr = self.sums.T
        seen = n > 0
        spread = float(np.sum(bb[seen] - b[seen] ** 2 / n[seen]))
        return float(np.sqrt(rr.sum() / spread)) if spread > 0 else None

    def widened(self, covariance: npt.NDArray[np.float64], description: str,
                inverse: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], str]:
        """On noise-free data (`relative` below `CLEAN_RELATIVE`), each variance at least
        the bound of an error as large as the whole misfit, and the description saying so;
        both unchanged elsewhere.

        The misfit is then the integrators' error (the record's own, the weak rows'
        quadrature): smooth and shared by every row, not noise. Row errors e move theta by
        e' W A M^-1, so parameter k by at most sqrt(M^-1_kk * e' W e) (Cauchy-Schwarz),
        with e' W e taken as the misfit: the classical covariance times the residual
        degrees of freedom, as the refinement's on noise-free data (`hamid.refine`).
        """
        relative = self.relative
        if relative is None or relative >= CLEAN_RELATIVE:
            return covariance, description
        widened = at_least(covariance, inverse * self.weighted)
        return widened, description + (
            f"; each variance at least the inverse normal matrix times the whole weighted misfit "
            f"({self.weighted:.3g}): noise-free data (energy rows' residual rms "
            f"{relative:.2g} of their spread), whose misfit is the integrators' error, "
            "shared by all rows")


def at_least(covariance: npt.NDArray[np.float64], other: npt.NDArray[np.float64]
             ) -> npt.NDArray[np.float64]:
    """`covariance` with each variance the larger of its own and `other`'s, and its
    correlations kept."""
    old = np.sqrt(np.clip(np.diag(covariance), 0, None))
    new = np.sqrt(np.maximum(np.diag(covariance), np.diag(other)))
    ratio = np.divide(new, old, out=np.ones_like(new), where=old > 0)
    return covariance * np.outer(ratio, ratio)
