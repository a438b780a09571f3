"""Two evaluable forms of a scalar function of the state, made by `hamid.model.parsing`.

A polynomial is a `Polynomial`, evaluated and differentiated with numpy alone, so built-in
models and polynomial expression models never import sympy and expose their monomials
(which bias correction needs). Anything else is a `Symbolic` function backed by sympy.
Several functions of one kind evaluate together as a `Stack` (`Func.stack`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    import sympy

__all__ = ["Func", "Polynomial", "Stack", "Symbolic", "Terms", "kinks"]

# A polynomial's terms: the exponents of each monomial (one per variable), its coefficient.
Terms = dict[tuple[int, ...], float]
# A sum this small against the sum of its terms' sizes is zero up to rounding.
_ZERO_TOLERANCE = 1e-10

# --- evaluable functions of the state ---------------------------------------------------

class Func:
    """A scalar function of the state variables, evaluated on whole arrays.

    `variables` names the columns of the state array `X`, shape (n_samples, n_variables).
    """

    variables: tuple[str, ...]

    def __call__(self, X: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        raise NotImplementedError

    def diff(self, name: str) -> Func:
        """The partial derivative with respect to one variable."""
        raise NotImplementedError

    def velocity_degrees(self, velocities: Sequence[str]) -> dict[int, Func] | None:
        """Split into parts homogeneous of degree 0, 1, 2, ... in the velocities.

        Returns None when the function is not polynomial in the velocities.
        """
        raise NotImplementedError

    def is_zero(self) -> bool:
        raise NotImplementedError

    def over(self, variables: tuple[str, ...]) -> Func:
        """The same function of more variables, which begin with its own (the state's,
        then the inputs), so that functions of the state and of the inputs stack together
        (`Func.stack` takes functions of the same variables)."""
        raise NotImplementedError

    def is_constant_in(self, names: Sequence[str]) -> bool:
        """Whether the function does not change with any of the named variables."""
        return all(self.diff(name).is_zero() for name in names)

    @staticmethod
    def combine(funcs: Sequence[Func], weights: Sequence[float]) -> Func:
        """The linear combination sum_k weights[k] * funcs[k] of functions of one kind."""
        kinds = {type(f) for f in funcs}
        if len(kinds) != 1:
            raise TypeError("cannot combine functions of different kinds")
        return kinds.pop()._combine(funcs, weights)

    @staticmethod
    def stack(funcs: Sequence[Func]) -> Stack:
        """One compiled evaluation of several functions of one kind and the same variables.

        The returned callable takes the state with the variables on the first axis,
        ``Xt`` of shape (n_variables, ...), and returns shape (len(funcs), ...). It is much
        faster than calling each function, since the work they share is done once.
        """
        kinds = {type(f) for f in funcs}
        if len(kinds) != 1:
            raise TypeError("cannot stack functions of different kinds")
        return kinds.pop()._stack(funcs)


class Stack:
    """Several functions evaluated together (`Func.stack`)."""

    n_funcs: int

    def __call__(self, Xt: npt.NDArray[np.float64]) -> np.ndarray:
        raise NotImplementedError

    def combined(self, K: npt.NDArray[np.float64]
                 ) -> Callable[[npt.NDArray[np.float64]], np.ndarray]:
        """Linear combinations of the functions, their own for each state.

        `K` (G, n_funcs, n) is fixed; the returned callable takes n states ``Xt``
        (n_variables, n) and returns shape (G, n): sum_k K[g, k, j] f_k(Xt[:, j]). Here
        the values weighed at every call; polynomials fold K into their coefficients once.
        """
        return lambda Xt: np.einsum("gkn,kn->gn", K, self(Xt))


@dataclass(frozen=True, eq=False)
class Polynomial(Func):
    """A polynomial: coefficients (n_terms,) times monomials with exponents (n_terms, n_vars)."""

    variables: tuple[str, ...]
    exponents: npt.NDArray[np.int64]
    coefficients: npt.NDArray[np.float64]

    @classmethod
    def from_terms(cls, terms: Terms, variables: Sequence[str]) -> Polynomial:
        keys = sorted(terms, key=lambda k: (sum(k), tuple(-e for e in k)))
        exponents = np.array(keys, dtype=np.int64).reshape(len(keys), len(variables))
        coefficients = np.array([terms[k] for k in keys], dtype=np.float64)
        return cls(tuple(variables), exponents, coefficients)

    def __call__(self, X: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        X = np.asarray(X, dtype=np.float64)
        return self._evaluator(np.moveaxis(X, -1, 0))[0]

    @cached_property
    def _evaluator(self) -> _PolynomialStack:
        """The table-of-monomials evaluation of `Func.stack`, built once per polynomial."""
        return _PolynomialStack([self])

    def diff(self, name: str) -> Polynomial:
        j = self.variables.index(name)
        keep = self.exponents[:, j] > 0
        exponents = self.exponents[keep].copy()
        coefficients = self.coefficients[keep] * exponents[:, j]
        exponents[:, j] -= 1
        return Polynomial(self.variables, exponents, coefficients)

    def velocity_degrees(self, velocities: Sequence[str]) -> dict[int, Func]:
        columns = [self.variables.index(v) for v in velocities]
        degree = self.exponents[:, columns].sum(axis=1)
        return {
            int(d): Polynomial(self.variables, self.exponents[degree == d],
                               self.coefficients[degree == d])
            for d in np.unique(degree)
        }

    def is_zero(self) -> bool:
        return not np.any(self.coefficients)

    def over(self, variables: tuple[str, ...]) -> Polynomial:
        assert variables[:len(self.variables)] == self.variables
        exponents = np.zeros((len(self.exponents), len(variables)), dtype=np.int64)
        exponents[:, :len(self.variables)] = self.exponents
        return Polynomial(variables, exponents, self.coefficients)

    @classmethod
    def _combine(cls, funcs: Sequence[Func], weights: Sequence[float]) -> Polynomial:
        terms: Terms = {}
        for f, w in zip(funcs, weights, strict=True):
            assert isinstance(f, Polynomial)
            for row, c in zip(f.exponents, f.coefficients, strict=True):
                key = tuple(int(e) for e in row)
                terms[key] = terms.get(key, 0.0) + w * c
        terms = {k: c for k, c in terms.items() if c != 0.0}
        return cls.from_terms(terms, funcs[0].variables)

    @classmethod
    def _stack(cls, funcs: Sequence[Func]) -> _PolynomialStack:
        return _PolynomialStack(funcs)

    def text(self) -> str:
        """The polynomial as an expression string, e.g. ``0.5*x**2 - 2*x*y``."""
        return _terms_text({tuple(int(e) for e in row): c for row, c in
                            zip(self.exponents, self.coefficients, strict=True)},
                           self.variables)


class _PolynomialStack(Stack):
    """Several polynomials as one table of their monomials times one coefficient matrix.

    The table holds the constant (if used), every variable, then the monomials of degree
    2, 3, ... Each monomial of degree d is a monomial of degree d - 1 times one variable;
    those sharing that variable come from consecutive rows, so one vectorised
    multiplication per degree and variable builds the table, however many monomials.
    """

    _CHUNK = 1 << 14  # samples per pass, so that the table stays in cache

    def __init__(self, funcs: Sequence[Func]):
        n_vars = len(funcs[0].variables)
        keys: set[tuple[int, ...]] = set()
        for f in funcs:
            assert isinstance(f, Polynomial)
            keys.update(tuple(int(e) for e in row) for row in f.exponents)
        pending = [k for k in keys if sum(k) > 1]
        while pending:
            parent = self._parent(pending.pop())[0]
            if sum(parent) > 1 and parent not in keys:
                keys.add(parent)
                pending.append(parent)
        self.constant = (0,) * n_vars in keys
        offset = int(self.constant)
        unit = [tuple(int(i == j) for i in range(n_vars)) for j in range(n_vars)]
        order = [(0,) * n_vars] * offset + unit
        self.levels: list[tuple[slice, slice | np.ndarray, slice]] = []
        index = {k: i for i, k in enumerate(order)}
        for degree in range(2, max((sum(k) for k in keys), default=0) + 1):
            # grouped by the variable that multiplies the parent, parents in table order:
            # each group is then usually one multiplication of consecutive rows (a view)
            level = sorted((self._parent(k)[1], index[self._parent(k)[0]], k)
                           for k in keys if sum(k) == degree)
            for j, group in itertools.groupby(level, key=lambda item: item[0]):
                members = list(group)
                start = len(order)
                order += [k for _, _, k in members]
                index.update((k, start + i) for i, (_, _, k) in enumerate(members))
                self.levels.append((slice(start, len(order)),
                                    _as_slice([parent for _, parent, _ in members]),
                                    slice(j, j + 1)))
        self.n_variables = n_vars
        self.n_rows = len(order)
        self.n_funcs = len(funcs)
        self.coefficients = np.zeros((len(funcs), len(order)))
        for i, f in enumerate(funcs):
            assert isinstance(f, Polynomial)
            for row, c in zip(f.exponents, f.coefficients, strict=True):
                self.coefficients[i, index[tuple(int(e) for e in row)]] += c

    @staticmethod
    def _parent(key: tuple[int, ...]) -> tuple[tuple[int, ...], int]:
        """The monomial of one degree less, and the variable that multiplies it back."""
        j = max(i for i, e in enumerate(key) if e)
        return key[:j] + (key[j] - 1,) + key[j + 1:], j

    def __call__(self, Xt: npt.NDArray[np.float64]) -> np.ndarray:
        Xt = np.asarray(Xt, dtype=np.float64)
        if Xt.ndim == 2 and Xt.shape[1] <= self._CHUNK:  # the common small case, kept lean
            return self.coefficients @ self.table(Xt)
        shape = Xt.shape[1:]
        flat = Xt.reshape(self.n_variables, -1)
        size = flat.shape[1]
        if size <= self._CHUNK:
            return (self.coefficients @ self.table(flat)).reshape(-1, *shape)
        out = np.empty((len(self.coefficients), size))
        for start in range(0, size, self._CHUNK):
            part = flat[:, start:start + self._CHUNK]
            out[:, start:start + part.shape[1]] = self.coefficients @ self.table(part)
        return out.reshape(-1, *shape)

    def combined(self, K: npt.NDArray[np.float64]
                 ) -> Callable[[npt.NDArray[np.float64]], np.ndarray]:
        """As `Stack.combined`, K folded into the coefficients once: a call costs one
        product per monomial and output (the trajectory refinement's equations, whose
        parameters differ from copy to copy of a segment), not one per function."""
        folded = np.einsum("gkn,kr->grn", K, self.coefficients)   # (G, monomials, n)
        return lambda Xt: np.einsum("grn,rn->gn", folded, self.table(Xt))

    def table(self, flat: np.ndarray) -> np.ndarray:
        """The monomials (rows) at the states `flat` (n_variables, n)."""
        table = np.empty((self.n_rows, flat.shape[1]))
        if self.constant:
            table[0] = 1.0
        table[int(self.constant):self.n_variables + int(self.constant)] = flat
        for rows, parents, variables in self.levels:
            np.multiply(table[parents], flat[variables], out=table[rows])
        return table


def _as_slice(rows: Sequence[int]) -> slice | np.ndarray:
    """Rows as a slice when they are consecutive (a view is cheaper than fancy indexing)."""
    if all(b - a == 1 for a, b in itertools.pairwise(rows)):
        return slice(rows[0], rows[-1] + 1)
    return np.array(rows, dtype=np.intp)


def _terms_text(terms: Terms, names: Sequence[str]) -> str:
    parts = []
    for key, coefficient in terms.items():
        factors = [n if e == 1 else f"{n}**{e}" for n, e in zip(names, key, strict=True) if e]
        if not factors:
            parts.append(f"{coefficient:g}")
        elif coefficient == 1.0:
            parts.append("*".join(factors))
        else:
            parts.append("*".join([f"{coefficient:g}", *factors]))
    return " + ".join(parts).replace("+ -", "- ") or "0"


@dataclass(frozen=True, eq=False)
class Symbolic(Func):
    """A sympy expression of the state variables, compiled to numpy on first use."""

    variables: tuple[str, ...]
    expression: sympy.Expr

    @cached_property
    def _compiled(self) -> Any:
        import sympy

        symbols = [sympy.Symbol(v, real=True) for v in self.variables]
        return sympy.lambdify(symbols, self.expression, modules="numpy", cse=True)

    def __call__(self, X: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        X = np.asarray(X, dtype=np.float64)
        with np.errstate(all="ignore"):
            value = np.asarray(self._compiled(*np.moveaxis(X, -1, 0)))
        if np.iscomplexobj(value):
            # A real formula can still give complex numbers (the square root of a negative
            # constant): outside the energy's domain, like numpy's sqrt(-1) = nan.
            value = np.where(value.imag == 0, value.real, np.nan)
        return np.broadcast_to(value.astype(np.float64), X.shape[:-1]).copy()

    def diff(self, name: str) -> Symbolic:
        """The derivative almost everywhere: that of sign(x), a Dirac delta at x = 0 (a
        set of measure zero that no sample lands on), is left out."""
        import sympy

        derivative = sympy.diff(self.expression, sympy.Symbol(name, real=True))
        return Symbolic(self.variables, derivative.replace(sympy.DiracDelta,
                                                           lambda *args: sympy.Integer(0)))

    def velocity_degrees(self, velocities: Sequence[str]) -> dict[int, Func] | None:
        import sympy

        scale = sympy.Dummy("s")
        scaled = self.expression.subs(
            {sympy.Symbol(v, real=True): scale * sympy.Symbol(v, real=True) for v in velocities},
            simultaneous=True)
        try:
            poly = sympy.Poly(sympy.expand(scaled), scale)
        except sympy.PolynomialError:
            return None
        if any(c.has(scale) for c in poly.coeffs()):
            return None
        return {int(m[0]): Symbolic(self.variables, c) for m, c in poly.terms()}

    def is_zero(self) -> bool:
        """Whether the expression vanishes identically: as sympy writes it, else at every
        one of a set of random points (mixed signs, and positive ones inside domains such
        as sqrt's) where it is defined, to rounding on the scale of its terms.

        sympy.simplify decided this before and took minutes on some short energies (a
        cube of five functions); the points take milliseconds.
        """
        import sympy

        if self.expression == 0:
            return True
        terms = sympy.Add.make_args(self.expression)
        symbols = [sympy.Symbol(v, real=True) for v in self.variables]
        compiled = sympy.lambdify(symbols, list(terms), modules="numpy")
        points = np.random.default_rng(0).standard_normal((len(self.variables), 32))
        points[:, 16:] = np.abs(points[:, 16:]) + 0.1
        with np.errstate(all="ignore"):
            values = np.array([np.broadcast_to(np.asarray(v, dtype=complex), points.shape[1:])
                               for v in compiled(*points)])
        total, scale = np.abs(values.sum(axis=0)), np.abs(values).sum(axis=0)
        defined = np.isfinite(total) & np.isfinite(scale)
        return bool(defined.any()) and bool(np.all(total[defined]
                                                   <= _ZERO_TOLERANCE * scale[defined]))

    def over(self, variables: tuple[str, ...]) -> Symbolic:
        assert variables[:len(self.variables)] == self.variables
        return Symbolic(variables, self.expression)

    @classmethod
    def _combine(cls, funcs: Sequence[Func], weights: Sequence[float]) -> Symbolic:
        import sympy

        total = sympy.Add(*[sympy.Float(w) * f.expression for f, w in zip(funcs, weights,
                                                                            strict=True)])
        return cls(funcs[0].variables, total)

    @classmethod
    def _stack(cls, funcs: Sequence[Func]) -> Stack:
        import sympy

        expressions = []
        for f in funcs:
            assert isinstance(f, Symbolic)
            expressions.append(f.expression)
        symbols = [sympy.Symbol(v, real=True) for v in funcs[0].variables]
        # one function, so that subexpressions common to several functions are shared
        return _CompiledStack(sympy.lambdify(symbols, expressions, modules="numpy", cse=True),
                              len(funcs))


class _CompiledStack(Stack):
    """Symbolic functions compiled together by sympy."""

    def __init__(self, compiled: Callable[..., Any], n_funcs: int):
        self._compiled, self.n_funcs = compiled, n_funcs

    def __call__(self, Xt: npt.NDArray[np.float64]) -> np.ndarray:
        Xt = np.asarray(Xt, dtype=np.float64)
        out = np.empty((self.n_funcs, *Xt.shape[1:]))
        with np.errstate(all="ignore"):
            for i, value in enumerate(self._compiled(*Xt)):
                value = np.asarray(value)
                if np.iscomplexobj(value):  # outside the domain, as in Symbolic.__call__
                    value = np.where(value.imag == 0, value.real, np.nan)
                out[i] = value
        return out


def kinks(expression: sympy.Expr, variables: Sequence[str]) -> list[Symbolic]:
    """Where a function is not smooth: the arguments of abs and sign, and the bases of
    fractional powers, each a function whose zero is a kink (or a singular force)."""
    import sympy

    found = []
    for node in sympy.preorder_traversal(expression):
        if isinstance(node, sympy.Abs | sympy.sign):
            found.append(node.args[0])
        elif (isinstance(node, sympy.Pow) and node.exp.is_number
              and not node.exp.is_integer):
            found.append(node.base)
    return [Symbolic(tuple(variables), f) for f in dict.fromkeys(found)
            if f.free_symbols & {sympy.Symbol(v, real=True) for v in variables}]

