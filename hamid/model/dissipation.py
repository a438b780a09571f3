"""Rayleigh's dissipation function: the forces that take energy out of a model.

R(q, v) = sum_k c_k R_k(q, v) is linear in its coefficients c_k. The dissipative force on
coordinate i is F_i = -dR/dv_i, and the power dissipated is -F.v = sum_i v_i dR/dv_i
(docs/method.md, "Damping: the energy balance"). A model file may give R in its
``[damping]`` table, e.g. joint friction between two arms:

    [damping]
    dissipation = "k1*omega1**2/2 + k2*(omega2 - omega1)**2/2"
    parameters = ["k1", "k2"]

and ``--damping viscous|coulomb|quadratic`` is shorthand for one term per coordinate:
c_q v**2/2, mu_q abs(v) and d_q abs(v)**3/3, whose forces are -c v, -mu sign(v) and
-d |v| v. Both go through the safe expression parser (`hamid.model.parsing`) as one function, so
the energy balance, the weak-form rows, the refinement and the simulator see one kind of
dissipation, however it was written.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from hamid.errors import ModelError
from hamid.model import expressions, parsing

__all__ = ["SHORTHAND", "Dissipation", "shorthand_names"]

Array = npt.NDArray[np.float64]

# kind -> (coefficient prefix, the term of R per unit coefficient in the velocity {v})
SHORTHAND: dict[str, tuple[str, str]] = {
    "viscous": ("c", "{v}**2/2"),
    "coulomb": ("mu", "abs({v})"),
    "quadratic": ("d", "abs({v})**3/3"),
}


def shorthand_names(coordinates: Sequence[str]) -> dict[str, tuple[str, int]]:
    """Every shorthand coefficient name a model allows -> (kind, coordinate index)."""
    return {f"{prefix}_{q}": (kind, i) for kind, (prefix, _) in SHORTHAND.items()
            for i, q in enumerate(coordinates)}


@dataclass(frozen=True, eq=False)
class Dissipation:
    """R = sum_k c_k R_k over the state (coordinates, velocities); no terms: conservative.

    `function` and `parameters` are the model file's own R (None and () without one);
    `names` are every coefficient, the model file's first, then the shorthand ones.
    """

    coordinates: tuple[str, ...]
    velocities: tuple[str, ...]
    names: tuple[str, ...] = ()
    parts: tuple[expressions.Func, ...] = ()
    function: str | None = None
    parameters: tuple[str, ...] = ()

    @classmethod
    def build(cls, coordinates: Sequence[str], velocities: Sequence[str], *,
              function: str | None = None, parameters: Sequence[str] = (),
              shorthand: Sequence[str] = (), where: str = "[damping]") -> Dissipation:
        """R from a model file's function of `parameters` plus shorthand coefficients
        (names such as ``c_x``, `shorthand_names`)."""
        coordinates, velocities = tuple(coordinates), tuple(velocities)
        allowed = shorthand_names(coordinates)
        unknown = [name for name in shorthand if name not in allowed]
        if unknown:
            raise ModelError(f"{where}: not damping coefficients of this model: "
                             f"{', '.join(unknown)}")
        clash = sorted(set(parameters) & set(shorthand))
        if clash:
            raise ModelError(f"{where}: {', '.join(clash)} is both a parameter of the "
                             "dissipation function and a --damping coefficient; rename it")
        terms = [f"({function})"] if function is not None else []
        for name in shorthand:
            kind, i = allowed[name]
            terms.append(f"{name}*{SHORTHAND[kind][1].format(v=velocities[i])}")
        names = (*parameters, *shorthand)
        if not terms:
            return cls(coordinates, velocities)
        tree = parsing.parse(" + ".join(terms), [*coordinates, *velocities, *names],
                             where=f"{where}: dissipation")
        _, parts = parsing.split_linear(tree, coordinates + velocities, names,
                                        where=f"{where}: dissipation", what="dissipation")
        return cls(coordinates, velocities, names, parts, function, tuple(parameters))

    def with_kinds(self, kinds: Sequence[str]) -> Dissipation:
        """This R plus the shorthand terms of `kinds` (``--damping``), kind by kind and
        coordinate by coordinate."""
        return self.with_shorthand([f"{SHORTHAND[kind][0]}_{q}" for kind in kinds
                                    for q in self.coordinates])

    def with_shorthand(self, names: Sequence[str]) -> Dissipation:
        """This R plus shorthand terms by coefficient name (``c_x``, `shorthand_names`)."""
        if not names:
            return self
        return Dissipation.build(self.coordinates, self.velocities, function=self.function,
                                 parameters=self.parameters,
                                 shorthand=[*self.names[len(self.parameters):], *names])

    def __len__(self) -> int:
        return len(self.names)

    @property
    def n(self) -> int:
        return len(self.coordinates)

    @property
    def variables(self) -> tuple[str, ...]:
        return self.coordinates + self.velocities

    @cached_property
    def _forces(self) -> Callable[[Array], Array]:
        """dR_k/dv_i of every part k and velocity i, in one compiled call."""
        return expressions.Func.stack([part.diff(v) for part in self.parts
                                       for v in self.velocities])

    @cached_property
    def _slopes(self) -> Callable[[Array], Array]:
        """d(dR_k/dv_i)/dx_c of every part k, velocity i and state variable c."""
        return expressions.Func.stack([part.diff(v).diff(x) for part in self.parts
                                for v in self.velocities for x in self.variables])

    def force_parts(self, X: Array) -> Array:
        """dR_k/dv_i at the states X (n, 2N): shape (n, N, K)."""
        values = _evaluate(self._forces, X)
        return values.reshape(len(self), self.n, len(X)).transpose(2, 1, 0)

    def power_parts(self, X: Array) -> Array:
        """sum_i v_i dR_k/dv_i at the states X (n, 2N): the power each coefficient
        dissipates, shape (n, K)."""
        return np.einsum("nik,ni->nk", self.force_parts(X), X[:, self.n:])

    def force_slopes(self, X: Array, coefficients: Array) -> Array:
        """d(-F_i)/dx_c = sum_k c_k d(dR_k/dv_i)/dx_c at states X (n, 2N): (n, N, 2N)."""
        values = _evaluate(self._slopes, X).reshape(len(self), self.n, 2 * self.n, len(X))
        return np.einsum("kicn,k->nic", values, np.asarray(coefficients, dtype=np.float64))

    def power_slopes(self, X: Array, coefficients: Array) -> Array:
        """d(sum_k c_k power_k)/dx_c at states X (n, 2N), shape (n, 2N): the product rule
        on sum_i v_i dR/dv_i."""
        c = np.asarray(coefficients, dtype=np.float64)
        slopes = np.einsum("nic,ni->nc", self.force_slopes(X, c), X[:, self.n:])
        slopes[:, self.n:] += self.force_parts(X) @ c
        return slopes

    @cached_property
    def reversals(self) -> tuple[expressions.Func, ...]:
        """The arguments of abs in R, each a function of the state whose sign change
        reverses a force of constant size (friction's): `smoothed` rounds them."""
        symbolic = [part for part in self.parts if isinstance(part, expressions.Symbolic)]
        if not symbolic:   # polynomials: no abs, and no sympy to import
            return ()
        import sympy

        found = [node.args[0] for part in symbolic
                 for node in sympy.preorder_traversal(part.expression)
                 if isinstance(node, sympy.Abs)]
        return tuple(expressions.Symbolic(self.variables, f) for f in dict.fromkeys(found))

    def smoothed(self, widths: Sequence[float]) -> Dissipation:
        """This R with each reversal g (`reversals`) rounded over its width w:
        abs(g) -> sqrt(g**2 + w**2), whose slope g / sqrt(g**2 + w**2) rounds sign(g).

        The forces then differ from the exact ones by at most their coefficient where
        |g| < w, and by about a coefficient times w**2 / (2 g**2) beyond: a law the
        trajectory refinement's integrator can step through, where a force that jumps
        at every reversal makes it take tiny steps without end."""
        import sympy

        rounded = {f.expression: w for f, w in zip(self.reversals, widths, strict=True)}

        def smooth(expression: sympy.Expr) -> sympy.Expr:
            return expression.replace(
                sympy.Abs, lambda g: sympy.sqrt(g**2 + sympy.Float(rounded[g])**2))

        parts = tuple(expressions.Symbolic(part.variables, smooth(part.expression))
                      if isinstance(part, expressions.Symbolic) else part
                      for part in self.parts)
        return dataclasses.replace(self, parts=parts)

    @cached_property
    def kinks(self) -> tuple[tuple[expressions.Func, ...], ...]:
        """Per part, the functions of the state at whose zeros it is not smooth (the
        arguments of abs and sign): integrals over time are split there."""
        return tuple(tuple(expressions.kinks(part.expression, self.variables))
                     if isinstance(part, expressions.Symbolic) else () for part in self.parts)


def _evaluate(stack: Callable[[Array], Array], X: Array) -> Array:
    """A stack's values at the states X (n, 2N), constant entries broadcast: (funcs, n)."""
    values = stack(np.asarray(X, dtype=np.float64).T)
    return np.broadcast_to(values, (len(values), len(X)))
