"""Energy expressions: a safe parser and two evaluable forms of a scalar function.

User text is parsed with Python's `ast` under a whitelist (numbers, declared names, `pi`,
+ - * / **, parentheses and a few functions) and never evaluated. A polynomial
expression becomes a `Polynomial`, evaluated and differentiated with numpy alone, so
built-in models and polynomial expression models never import sympy and expose their
monomials (which bias correction needs). Anything else becomes a `Symbolic` function
backed by sympy.
"""

from __future__ import annotations

import ast
import itertools
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from hamid.errors import ModelError

if TYPE_CHECKING:
    import sympy

__all__ = [
    "FUNCTIONS",
    "MAX_EXPONENT",
    "MAX_LENGTH",
    "Func",
    "Polynomial",
    "Stack",
    "Symbolic",
    "parse",
    "split_linear",
]

FUNCTIONS = ("sqrt", "exp", "log", "sin", "cos", "tan", "sinh", "cosh", "tanh", "abs")
CONSTANTS = {"pi": math.pi}
MAX_LENGTH = 10_000
MAX_EXPONENT = 64
MAX_DEPTH = 500  # nesting of the syntax tree; deeper trees would exhaust the Python stack
MAX_NESTING = 100  # as sympy nests: sin(sin(...)) 135 deep exhausts its derivatives' stack
_FAMILIES = {ast.Add: "+", ast.Sub: "+", ast.Mult: "*"}
MAX_TERMS = 10_000  # monomials an expanded energy may have, against blow-up
MAX_DEGREE = 256  # total degree of an expanded energy (Polynomial tabulates every power)
# A sum this small against the sum of its terms' sizes is zero up to rounding.
_ZERO_TOLERANCE = 1e-10

_OPERATORS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Pow: "**"}
_FORBIDDEN = {
    ast.Attribute: "attribute access",
    ast.Lambda: "lambda",
    ast.ListComp: "a comprehension",
    ast.SetComp: "a comprehension",
    ast.DictComp: "a comprehension",
    ast.GeneratorExp: "a comprehension",
    ast.Subscript: "indexing",
    ast.Compare: "a comparison",
    ast.BoolOp: "a boolean operator",
    ast.IfExp: "a conditional",
    ast.NamedExpr: "an assignment",
    ast.Starred: "a starred argument",
}


def parse(text: str, names: Sequence[str] | None, *, where: str = "energy") -> ast.expr:
    """Parse and check an expression; only whitelisted syntax and `names` may appear.

    Parameters
    ----------
    text : str
        The expression, e.g. ``"v**2/2 + k*x**2/2"``.
    names : sequence of str or None
        The symbols the expression may use (coordinates, velocities, parameters); None
        allows any name that is not a function.
    where : str
        What the text is, for error messages (e.g. ``"model.toml: energy"``).

    Returns
    -------
    ast.expr
        The checked syntax tree.
    """
    if not isinstance(text, str) or not text.strip():
        raise ModelError(f"{where}: the expression is empty")
    if len(text) > MAX_LENGTH:
        raise ModelError(f"{where}: the expression is {len(text)} characters long "
                         f"(at most {MAX_LENGTH})")
    # Python folds names to NFKC, so a full-width 'ｋ' would silently be the parameter 'k'.
    foreign = next((c for c in text if not c.isascii()), None)
    if foreign is not None:
        raise ModelError(f"{where}: {foreign!r} (U+{ord(foreign):04X}) is not ASCII; "
                         "names, numbers and operators are written in ASCII")
    if "#" in text:   # Python would read the rest as a comment and drop it silently
        raise ModelError(f"{where}: '#' (character {text.index('#') + 1}) is not allowed "
                         f"in an expression: {text.strip()[:60]!r}")
    try:
        with warnings.catch_warnings():
            # Python would print a warning about text such as '1if x' on standard error;
            # such text is refused instead.
            warnings.simplefilter("error", SyntaxWarning)
            warnings.simplefilter("error", DeprecationWarning)
            # line breaks are spaces (a long energy over several lines of a TOML string)
            tree = ast.parse(" ".join(text.split()), mode="eval").body
    except (SyntaxError, ValueError, MemoryError, RecursionError) as exc:
        detail = getattr(exc, "msg", None) or str(exc) or type(exc).__name__
        raise ModelError(f"{where}: cannot parse {text.strip()!r}: {detail}") from exc
    depth, nesting, stack = 0, 0, [(tree, 0, 0, None)]
    while stack:   # sympy flattens a + b - c and a*b*c: nesting counts them as one level
        node, level, nested, outer = stack.pop()
        family = _FAMILIES.get(type(getattr(node, "op", None)))
        nested += family is None or family != outer
        depth, nesting = max(depth, level + 1), max(nesting, nested)
        stack.extend((child, level + 1, nested, family) for child in ast.iter_child_nodes(node))
    found, most, what = (depth, MAX_DEPTH, "") if depth > MAX_DEPTH else (
        nesting, MAX_NESTING, " in functions, powers and brackets")
    if found > most:
        raise ModelError(f"{where}: the expression is nested {found} levels deep{what} "
                         f"(at most {most})")
    allowed = None if names is None else set(names)
    called = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and node.id in FUNCTIONS and id(node) not in called:
            raise ModelError(f"{where}: {node.id!r} is a function and needs an argument")
        _check_node(node, allowed, text, where)
    return tree


def _check_node(node: ast.AST, allowed: set[str] | None, text: str, where: str) -> None:
    """Reject any syntax outside the whitelist, naming the offending piece."""
    piece = ast.get_source_segment(text.strip(), node) or type(node).__name__
    if type(node) in _FORBIDDEN:
        raise ModelError(f"{where}: {_FORBIDDEN[type(node)]} is not allowed: {piece!r}")
    if isinstance(node, ast.Call):
        func = node.func
        if not isinstance(func, ast.Name):
            raise ModelError(f"{where}: only the functions {', '.join(FUNCTIONS)} may be "
                             f"called: {piece!r}")
        if func.id not in FUNCTIONS:
            raise ModelError(f"{where}: unknown function {func.id!r} in {piece!r} "
                             f"(allowed: {', '.join(FUNCTIONS)})")
        if len(node.args) != 1 or node.keywords:
            raise ModelError(f"{where}: {func.id}() takes exactly one argument: {piece!r}")
    elif isinstance(node, ast.Name):
        if node.id in FUNCTIONS or node.id in CONSTANTS or allowed is None or node.id in allowed:
            return
        raise ModelError(f"{where}: unknown symbol {node.id!r}")
    elif isinstance(node, ast.Constant):
        if isinstance(node.value, bool) or not isinstance(node.value, int | float):
            raise ModelError(f"{where}: only numbers may appear as constants: {piece!r}")
        try:
            finite = math.isfinite(node.value)
        except OverflowError:
            finite = False
        if not finite:
            raise ModelError(f"{where}: the number {piece!r} is too large")
    elif isinstance(node, ast.BinOp):
        if type(node.op) not in _OPERATORS:
            raise ModelError(f"{where}: operator not allowed in {piece!r} (use + - * / **)")
        if isinstance(node.op, ast.Pow):
            _check_exponent(node.right, text, where)
    elif isinstance(node, ast.UnaryOp):
        if not isinstance(node.op, ast.UAdd | ast.USub):
            raise ModelError(f"{where}: operator not allowed in {piece!r}")
    elif not isinstance(node, ast.expr_context | ast.operator | ast.unaryop):
        raise ModelError(f"{where}: {type(node).__name__.lower()} is not allowed: {piece!r}")


def _check_exponent(node: ast.expr, text: str, where: str) -> None:
    """An exponent must be a small constant, so that `x**10**10` cannot exhaust memory."""
    piece = ast.get_source_segment(text.strip(), node) or "?"
    value = _constant_value(node)
    if value is None:
        raise ModelError(f"{where}: the exponent {piece!r} must be a number")
    if not abs(value) <= MAX_EXPONENT:
        raise ModelError(f"{where}: the exponent {piece!r} is too large "
                         f"(at most {MAX_EXPONENT} in size)")


def _constant_value(node: ast.expr) -> float | None:
    """The value of a constant exponent: a number, a signed number or a ratio of numbers."""
    if isinstance(node, ast.Constant) and isinstance(node.value, int | float):
        try:
            return float(node.value)
        except OverflowError:
            return math.inf
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.UAdd | ast.USub):
        inner = _constant_value(node.operand)
        return inner if inner is None or isinstance(node.op, ast.UAdd) else -inner
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
        num, den = _constant_value(node.left), _constant_value(node.right)
        return None if num is None or den is None or den == 0 else num / den
    return None


# --- polynomial form --------------------------------------------------------------------

_Terms = dict[tuple[int, ...], float]


class _NotPolynomial(Exception):
    """Internal signal: the expression leaves the polynomial form."""


def _to_terms(node: ast.expr, index: Mapping[str, int]) -> _Terms:
    """Expand a checked tree into monomials over the symbols in `index`."""
    size = len(index)
    if isinstance(node, ast.Constant):
        return {(0,) * size: float(node.value)} if node.value else {}
    if isinstance(node, ast.Name):
        if node.id in CONSTANTS:
            return {(0,) * size: CONSTANTS[node.id]}
        exponents = [0] * size
        exponents[index[node.id]] = 1
        return {tuple(exponents): 1.0}
    if isinstance(node, ast.UnaryOp):
        inner = _to_terms(node.operand, index)
        return {k: -c for k, c in inner.items()} if isinstance(node.op, ast.USub) else inner
    if isinstance(node, ast.BinOp):
        left = _to_terms(node.left, index)
        if isinstance(node.op, ast.Pow):
            power = _constant_value(node.right)
            if power is None or power < 0 or power != int(power):
                raise _NotPolynomial
            return _power(left, int(power), size)
        right = _to_terms(node.right, index)
        if isinstance(node.op, ast.Add):
            return _add(left, right, 1.0)
        if isinstance(node.op, ast.Sub):
            return _add(left, right, -1.0)
        if isinstance(node.op, ast.Mult):
            return _multiply(left, right)
        if isinstance(node.op, ast.Div):
            if any(any(k) for k in right) or not right:
                raise _NotPolynomial
            divisor = right[(0,) * size]
            return {k: c / divisor for k, c in left.items()}
    raise _NotPolynomial


def _add(a: _Terms, b: _Terms, sign: float) -> _Terms:
    out = dict(a)
    for k, c in b.items():
        out[k] = out.get(k, 0.0) + sign * c
    return {k: c for k, c in out.items() if c != 0.0}


def _multiply(a: _Terms, b: _Terms) -> _Terms:
    out: _Terms = {}
    for ka, ca in a.items():
        for kb, cb in b.items():
            k = tuple(x + y for x, y in zip(ka, kb, strict=True))
            out[k] = out.get(k, 0.0) + ca * cb
    return {k: c for k, c in out.items() if c != 0.0}


def _power(a: _Terms, n: int, size: int) -> _Terms:
    out: _Terms = {(0,) * size: 1.0}
    for _ in range(n):
        out = _multiply(out, a)
    return out


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
    def from_terms(cls, terms: _Terms, variables: Sequence[str]) -> Polynomial:
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

    @classmethod
    def _combine(cls, funcs: Sequence[Func], weights: Sequence[float]) -> Polynomial:
        terms: _Terms = {}
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


def _terms_text(terms: _Terms, names: Sequence[str]) -> str:
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


# --- linear split -----------------------------------------------------------------------

def split_linear(tree: ast.expr, variables: Sequence[str], parameters: Sequence[str], *,
                 where: str = "energy", what: str = "energy",
                 required: Sequence[str] | None = None) -> tuple[Func, tuple[Func, ...]]:
    """Split an energy into its parameter-free part E0 and one basis function per parameter.

    Returns ``(E0, (phi_1, ..., phi_p))`` with E = E0 + sum_k theta_k phi_k. Raises a
    ModelError naming the offending term when E is not linear in the parameters, or when
    one of the `required` parameters (default: all) does not appear. With
    ``what="dissipation"`` (Rayleigh's dissipation function, `hamid.model.dissipation`) the
    parameter-free part must be zero: every dissipative term carries a coefficient to fit.
    A forcing's work (``what="work"``) may name any parameter, and needs only its gains."""
    names = [*variables, *parameters]
    _check_size(tree, where)
    try:
        terms = _to_terms(tree, {n: i for i, n in enumerate(names)})
    except _NotPolynomial:
        E0, phi = _split_symbolic(tree, variables, parameters, where, what)
    else:
        E0, phi = _split_polynomial(terms, variables, parameters, where, what)
    if what == "dissipation" and not E0.is_zero():
        raise ModelError(f"{where}: every term of the {what} needs one of its parameters "
                         "as a factor (it has a parameter-free part)")
    needed = parameters if required is None else required
    for name, f in zip(parameters, phi, strict=True):
        if name in needed and f.is_zero():
            raise ModelError(f"{where}: parameter {name!r} does not appear in the {what}")
    return E0, phi


def _check_size(tree: ast.expr, where: str) -> None:
    """Reject energies whose expansion would be huge, e.g. ``((x + y + 1)**64)**64``."""

    def size(node: ast.expr) -> tuple[int, int]:
        """Upper bounds on (number of monomials, total degree) once expanded."""
        if isinstance(node, ast.Constant):
            return 1, 0
        if isinstance(node, ast.UnaryOp):
            return size(node.operand)
        if isinstance(node, ast.Call):
            size(node.args[0])
        if not isinstance(node, ast.BinOp):
            return 1, 1
        (n_left, d_left), (n_right, d_right) = size(node.left), size(node.right)
        if isinstance(node.op, ast.Add | ast.Sub):
            n, d = n_left + n_right, max(d_left, d_right)
        elif isinstance(node.op, ast.Pow):
            power = math.ceil(abs(_constant_value(node.right) or 0.0))
            n, d = math.comb(n_left + power - 1, power), d_left * power
        else:
            n, d = n_left * n_right, d_left + d_right
        if n > MAX_TERMS or d > MAX_DEGREE:
            raise ModelError(f"{where}: {ast.unparse(node)!r} expands to too many terms "
                             f"(at most {MAX_TERMS} terms of degree at most {MAX_DEGREE})")
        return n, d

    size(tree)


def _split_polynomial(terms: _Terms, variables: Sequence[str], parameters: Sequence[str],
                      where: str, what: str) -> tuple[Func, tuple[Func, ...]]:
    n_vars = len(variables)
    parts: list[_Terms] = [{} for _ in range(len(parameters) + 1)]
    for key, coefficient in terms.items():
        powers = key[n_vars:]
        if sum(powers) > 1:
            involved = [p for p, e in zip(parameters, powers, strict=True) if e]
            term = _terms_text({key: coefficient}, [*variables, *parameters])
            raise ModelError(f"{where}: {what} term {term!r} is not linear in the parameters "
                             f"({', '.join(involved)})")
        slot = powers.index(1) + 1 if sum(powers) else 0
        parts[slot][key[:n_vars]] = coefficient
    funcs = [Polynomial.from_terms(p, variables) for p in parts]
    return funcs[0], tuple(funcs[1:])


def _split_symbolic(tree: ast.expr, variables: Sequence[str], parameters: Sequence[str],
                    where: str, what: str) -> tuple[Func, tuple[Func, ...]]:
    import sympy

    expression = to_sympy(tree)
    params = [sympy.Symbol(p, real=True) for p in parameters]
    parts = [sympy.Integer(0) for _ in range(len(parameters) + 1)]
    for term in sympy.Add.make_args(sympy.expand(expression)):
        if term.has(sympy.zoo, sympy.oo, -sympy.oo, sympy.nan):
            raise ModelError(f"{where}: {what} term {str(term)!r} is not finite "
                             "(a division by zero?)")
        if term.has(sympy.I):
            raise ModelError(f"{where}: {what} term {str(term)!r} is not real "
                             "(the square root or logarithm of a negative number?)")
        involved = [p for p in params if term.has(p)]
        if not involved:
            parts[0] += term
            continue
        factor = term / involved[0] if len(involved) == 1 else None
        if factor is None or factor.has(involved[0]):
            raise ModelError(f"{where}: {what} term {str(term)!r} is not linear in the "
                             f"parameters ({', '.join(str(p) for p in involved)})")
        parts[params.index(involved[0]) + 1] += factor
    funcs = [Symbolic(tuple(variables), p) for p in parts]
    return funcs[0], tuple(funcs[1:])


_SYMPY_FUNCTIONS = {"abs": "Abs"}


def to_sympy(tree: ast.expr) -> sympy.Expr:
    """Build the sympy expression of a checked tree, node by node (no `sympify` of text)."""
    import sympy

    def build(node: ast.expr) -> sympy.Expr:
        if isinstance(node, ast.Constant):
            value = node.value
            return sympy.Integer(value) if isinstance(value, int) else sympy.Float(value)
        if isinstance(node, ast.Name):
            return sympy.pi if node.id == "pi" else sympy.Symbol(node.id, real=True)
        if isinstance(node, ast.UnaryOp):
            inner = build(node.operand)
            return -inner if isinstance(node.op, ast.USub) else inner
        if isinstance(node, ast.BinOp):
            left, right = build(node.left), build(node.right)
            if isinstance(node.op, ast.Pow):
                value = _constant_value(node.right)
                if value is not None and value == int(value):
                    right = sympy.Integer(int(value))
                elif isinstance(node.right, ast.BinOp):
                    right = sympy.nsimplify(right)
            return {ast.Add: lambda: left + right, ast.Sub: lambda: left - right,
                    ast.Mult: lambda: left * right, ast.Div: lambda: left / right,
                    ast.Pow: lambda: left ** right}[type(node.op)]()
        if isinstance(node, ast.Call):
            assert isinstance(node.func, ast.Name)
            name = _SYMPY_FUNCTIONS.get(node.func.id, node.func.id)
            return getattr(sympy, name)(build(node.args[0]))
        raise ModelError(f"unsupported expression node {type(node).__name__}")

    return build(tree)


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


def symbols_in_order(tree: ast.expr) -> list[str]:
    """Names used in the expression, in order of first appearance (functions excluded)."""
    seen: dict[str, None] = {}
    functions = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Name) and id(node) not in functions and node.id not in CONSTANTS:
            seen.setdefault(node.id, None)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return list(seen)
