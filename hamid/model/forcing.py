"""Measured excitation: the virtual work W(q, u) of recorded inputs u on the coordinates.

A model file's ``[forcing]`` table names the inputs (columns of the recording), the work
and any unknown gains in it. The generalized force on q_i is Q_i = dW/dq_i with the inputs
held fixed; like the energy, W is linear in the parameters (the energy's and the gains),
so that Q = Q0 + sum_k theta_k Q_k enters the energy balance and Lagrange's equations as
columns of the same linear fit (docs/method.md, "Measured excitation").
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.errors import ModelError
from hamid.model import parsing
from hamid.model.expressions import Func
from hamid.model.toml_values import check_keys, table

__all__ = ["FORCING_KEYS", "Forcing", "parse_forcing"]

# Keys of a [forcing] table; `signals` is read by `hamid.simulate` only.
FORCING_KEYS = ("inputs", "work", "parameters", "signals")


@dataclass(frozen=True, eq=False)
class Forcing:
    """The recorded inputs of a model and their virtual work.

    `Q0[i]` and `Q[i][k]` are the parameter-free part of the generalized force on
    coordinate i and its part per model parameter k (`parameters`: the energy's, then the
    gains), functions of the state and the inputs side by side (coordinates, velocities,
    inputs).
    """

    inputs: tuple[str, ...]
    work: str
    gains: tuple[str, ...]
    parameters: tuple[str, ...]
    Q0: tuple[Func, ...]
    Q: tuple[tuple[Func, ...], ...]

    @property
    def has_known_part(self) -> bool:
        """Whether the work has a part without a parameter (``F*x``): the recorded force
        then fixes the energy's scale, and the parameters come out in physical units."""
        return any(not f.is_zero() for f in self.Q0)

    def parts(self, X: npt.NDArray[np.float64], U: npt.NDArray[np.float64]
              ) -> tuple[np.ndarray, np.ndarray]:
        """The generalized force at states X (n, 2N) and inputs U (n, m): its parameter-free
        part (n, N) and its part per parameter (n, N, P), Q = Q0 + Q_k theta_k."""
        joined = np.hstack([X, U])
        n, N = len(joined), len(self.Q0)
        Q0 = np.zeros((n, N))
        Q = np.zeros((n, N, len(self.parameters)))
        for i, f in enumerate(self.Q0):
            if not f.is_zero():
                Q0[:, i] = f(joined)
            for k, g in enumerate(self.Q[i]):
                if not g.is_zero():
                    Q[:, i, k] = g(joined)
        return Q0, Q

    def info(self) -> dict[str, Any]:
        """The plain description stored in reports (`Model.info`)."""
        return {"inputs": list(self.inputs), "work": self.work, "parameters": list(self.gains)}


def parse_forcing(value: Any, *, coordinates: Sequence[str], velocities: Sequence[str],
                  parameters: Sequence[str], where: str = "[forcing]") -> Forcing:
    """The forcing of a ``[forcing]`` table over a model's names; its gains follow the
    model's `parameters` in `Forcing.parameters`."""
    entries = table(value, where=where)
    check_keys(entries, FORCING_KEYS, where=where)
    inputs = _names(entries.get("inputs"), "inputs", where)
    if not inputs:
        raise ModelError(f"{where}: 'inputs' must list at least one input (a column of the "
                         "recording)")
    gains = _names(entries.get("parameters", []), "parameters", where)
    for name in (*inputs, *gains):
        taken = _taken_by(name, coordinates=coordinates, velocities=velocities,
                          parameters=parameters)
        if taken:
            raise ModelError(f"{where}: {name!r} cannot be an input or gain name: {taken}")
    twice = sorted({name for name in (*inputs, *gains) if (*inputs, *gains).count(name) > 1})
    if twice:
        raise ModelError(f"{where}: {twice[0]!r} is given twice in 'inputs' and 'parameters'")
    work = entries.get("work")
    if not isinstance(work, str):
        raise ModelError(f"{where}: 'work' must be an expression of the coordinates and "
                         "inputs, e.g. work = \"F*x\"")
    tree = parsing.parse(work, None, where=f"{where}: work")
    allowed = [*coordinates, *inputs, *parameters, *gains]
    for symbol in parsing.symbols_in_order(tree):
        if symbol not in allowed:
            lowered = {name.lower(): name for name in allowed}
            close = [lowered[m] for m in difflib.get_close_matches(symbol.lower(), lowered,
                                                                   n=1)]
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            velocity = ("; velocities may not appear in the work (it is W(q, u); a force "
                        "that depends on velocity belongs in [damping])"
                        if symbol in velocities else "")
            raise ModelError(f"{where}: work: unknown symbol {symbol!r}{hint}; it may use "
                             f"{', '.join(allowed)}{velocity}")
    every = (*parameters, *gains)
    W0, W = parsing.split_linear(tree, (*coordinates, *velocities, *inputs), every,
                                 where=f"{where}: work", what="work", required=gains)
    Q0 = tuple(W0.diff(q) for q in coordinates)
    Q = tuple(tuple(w.diff(q) for w in W) for q in coordinates)
    if all(f.is_zero() for f in Q0) and all(g.is_zero() for row in Q for g in row):
        raise ModelError(f"{where}: work {work!r} does not depend on any coordinate "
                         f"({', '.join(coordinates)}), so it exerts no force")
    return Forcing(inputs, work, gains, every, Q0, Q)


def _taken_by(name: str, *, coordinates: Sequence[str], velocities: Sequence[str],
              parameters: Sequence[str]) -> str:
    """What already owns `name` in the model or the parser ('' if nothing does)."""
    for owner, names in (("a coordinate", coordinates), ("a velocity", velocities),
                         ("a parameter of the model", parameters),
                         ("a function", parsing.FUNCTIONS),
                         ("a constant", parsing.CONSTANTS)):
        if name in names:
            return f"it is {owner}"
    return "" if name.isidentifier() else "it is not a name (letters, digits, _)"


def _names(value: Any, key: str, where: str) -> tuple[str, ...]:
    if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
        found = f", not the string {value[:40]!r}" if isinstance(value, str) else ""
        raise ModelError(f"{where}: {key!r} must be a list of names{found}")
    return tuple(value)
