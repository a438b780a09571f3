"""The parameters of a fit: the energy's, then the damping coefficients; which are held
fixed at known values and which are free, in the order of the estimate theta."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from hamid.errors import ModelError, UsageError
from hamid.linear.design import Block

if TYPE_CHECKING:
    from hamid.model.models import Model

__all__ = ["Unknowns"]


@dataclass(frozen=True)
class Unknowns:
    """Every parameter's name and role, and the values of those held fixed.

    `names` lists the model's energy parameters (the first `n_energy`), then the damping
    coefficients; `fixed` maps the names of the fixed ones to their values; `scale` says
    where the energy's scale comes from (the report's `method.scale`): ``energy`` (its
    parameter-free part), ``input`` (a recorded input with a known coefficient in the
    forcing's work: the parameters are then in the recording's physical units) or
    ``fixed`` (a parameter held at a known value), with the part that sets it.
    """

    names: tuple[str, ...]
    n_energy: int
    fixed: Mapping[str, float]
    scale: Mapping[str, str] = dataclasses.field(default_factory=dict)

    @classmethod
    def of(cls, model: Model, damping: Sequence[str], fix: Mapping[str, float]) -> Unknowns:
        """The unknowns of a model's energy parameters and damping coefficients, with `fix`
        (name -> value, from --fix) checked against them.

        An energy without a parameter-free part (``m*v**2/2 + k*x**2/2``) takes its scale
        from a parameter fixed at a value other than zero, or from a recorded force with a
        known coefficient (`Forcing.has_known_part`); with neither, every multiple of the
        parameters fits the motion alike."""
        energy = model.parameters
        names = (*energy, *damping)
        for name, value in fix.items():
            if name not in names:
                raise UsageError(f"--fix: {name!r} is not a parameter of the model "
                                 f"({', '.join(names)})")
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise UsageError(f"--fix: {name}={value!r} is not a finite number")
        if all(name in fix for name in names):
            raise UsageError("every parameter is fixed; nothing is left to fit")
        known = [name for name in energy if fix.get(name)]
        if model.forcing is not None and model.forcing.has_known_part:
            scale = {"source": "input", "by": model.forcing.work}
        elif not model.E0.is_zero():
            scale = {"source": "energy", "by": "the energy's parameter-free part"}
        elif known:
            scale = {"source": "fixed", "by": ", ".join(f"{name} = {fix[name]:g}"
                                                        for name in known)}
        else:
            raise ModelError(f"model {model.name!r}: the energy has no parameter-free part "
                             "(such as the kinetic energy), so its scale is undetermined; "
                             "fix one of its parameters (--fix NAME=VALUE, e.g. a known "
                             "mass)")
        return cls(names, len(energy), {name: float(value) for name, value in fix.items()},
                   scale)

    @cached_property
    def free(self) -> npt.NDArray[np.intp]:
        """Positions in `names` of the free parameters, the order of theta."""
        return np.array([k for k, name in enumerate(self.names) if name not in self.fixed],
                        dtype=np.intp)

    @property
    def free_names(self) -> list[str]:
        return [self.names[k] for k in self.free]

    @cached_property
    def fixed_values(self) -> npt.NDArray[np.float64]:
        """Every parameter's fixed value, 0 for the free ones."""
        return np.array([self.fixed.get(name, 0.0) for name in self.names])

    def role(self, k: int) -> str:
        """"energy" or "damping", for the parameter at position k of `names`."""
        return "energy" if k < self.n_energy else "damping"

    def full(self, theta: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """All parameters' values: the fixed ones, and theta for the free ones."""
        values = self.fixed_values.copy()
        values[self.free] = theta
        return values

    def estimates(self, theta: npt.NDArray[np.float64]) -> dict[str, float]:
        """Name -> value of every parameter, the fixed ones first."""
        return {**self.fixed, **dict(zip(self.free_names, theta.tolist(), strict=True))}

    def hold_fixed(self, block: Block) -> Block:
        """Move the terms of fixed parameters into the known side of the rows."""
        if len(self.free) == block.A.shape[1]:
            return block
        return dataclasses.replace(block, A=block.A[:, self.free],
                                   b=block.b - block.A @ self.fixed_values)
