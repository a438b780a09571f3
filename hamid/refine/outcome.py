"""What the trajectory refinement hands back (`Outcome`), and what the report says of it:
`RefinementInfo` is ``method.refinement`` of the fit's report (docs/output.md), as
`joint_refinement.refine` builds it and as `FitResult.method` holds it once read back.

Light on purpose: `hamid.result` reads these types without loading the refinement.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, NotRequired, TypedDict

if TYPE_CHECKING:
    from hamid.linear.estimate import LinearFit

__all__ = ["AcceptanceInfo", "LengtheningInfo", "NoiseLevel", "Outcome", "RefinementInfo",
           "SmoothingInfo"]


class NoiseLevel(TypedDict):
    """The noise one variable was weighted by in the trajectory refinement."""

    sigma: float | None                  # None: not weighted (derived velocities)
    source: Literal["given", "differences", "residuals", "derived"]


class AcceptanceInfo(TypedDict):
    """Why the refinement was kept or not: its held-out check against the linear fit."""

    rule: Literal["held-out", "noise"]
    folds: NotRequired[int]              # the rest with the held-out rule
    linear_refitted: NotRequired[bool]
    held_out_linear: NotRequired[float]
    held_out_refined: NotRequired[float]
    t: NotRequired[float]
    t_limit: NotRequired[float]


class LengtheningInfo(TypedDict):
    """The refinement's segments once lengthened (neighbours joined) within the noise."""

    segments: int
    segment_seconds: float               # the longest segment
    rounds: int                          # joins kept
    iterations: int                      # Gauss-Newton iterations of the last one kept
    chi2_per_dof: float
    stopped: Literal["whole", "longest", "misfit", "failed", "unstable", "clean"]


class SmoothingInfo(TypedDict):
    """A friction force's reversal as the refinement integrates it: rounded over `width`
    of its argument, the force's error relative to its size on average over the samples."""

    reversal: str            # the argument whose sign the force follows, e.g. "v"
    width: float
    mean_force_error: float


class RefinementInfo(TypedDict):
    """Whether the trajectory refinement of `auto` ran; its figures, or why not."""

    applied: bool
    reason: NotRequired[str]             # when not applied
    segments: NotRequired[int]           # the rest when applied (or fitted and refused)
    segment_seconds: NotRequired[float]
    iterations: NotRequired[int]
    chi2_per_dof: NotRequired[float]
    noise_chi2_per_dof: NotRequired[float]
    noise: NotRequired[dict[str, NoiseLevel]]
    covariance: NotRequired[Literal["misfit-scaled", "sandwich"]]
    acceptance: NotRequired[AcceptanceInfo]
    smoothing: NotRequired[list[SmoothingInfo]]   # friction's reversals rounded, if any
    # present once the fit passed its check; None: not lengthened (beyond the noise, or failed)
    lengthening: NotRequired[LengtheningInfo | None]


@dataclass(frozen=True, kw_only=True)
class Outcome:
    """What the refinement hands back: the refined fit, None when it is not kept, and what
    the report says of it (`method.refinement`: applied, the reason when not, the fit's
    segments, misfit, noise, held-out check and lengthening)."""

    fit: LinearFit | None
    report: RefinementInfo

    @classmethod
    def refused(cls, reason: str, **details: Any) -> Outcome:
        """The refinement not applied, or not kept, and why."""
        return cls(fit=None, report=RefinementInfo(applied=False, reason=reason, **details))

    @property
    def reason(self) -> str | None:
        """Why the refinement was not applied or not kept; None when it was."""
        return None if self.report["applied"] else self.report["reason"]
