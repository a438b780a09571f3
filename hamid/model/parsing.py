"""The safe parser of energy text: user text to a checked syntax tree, and a checked tree
to the evaluable forms of `hamid.model.expressions`.

User text is parsed with Python's `ast` under a whitelist (numbers, declared names, `pi`,
+ - * / **, parentheses and a few functions), within limits of length, nesting, exponents
and expanded size, and never evaluated. `split_linear` splits a tree linear in its
parameters into the parameter-free part and one function per parameter: a `Polynomial`
when the text is polynomial (expanded here into monomials, without sympy), a `Symbolic`
otherwise (built by `to_sympy`, node by node).
"""

from __future__ import annotations

import ast
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

from hamid.errors import ModelError
from hamid.model.expressions import Func, Polynomial, Symbolic, Terms

if TYPE_CHECKING:
    import sympy

__all__ = [
    "CONSTANTS",
    "FUNCTIONS",
    "MAX_EXPONENT",
    "MAX_LENGTH",
    "parse",
    "split_linear",
    "symbols_in_order",
    "to_sympy",
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


# --- polynomial terms -------------------------------------------------------------------

class _NotPolynomial(Exception):
    """Internal signal: the expression leaves the polynomial form."""


def _to_terms(node: ast.expr, index: Mapping[str, int]) -> Terms:
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


def _add(a: Terms, b: Terms, sign: float) -> Terms:
    out = dict(a)
    for k, c in b.items():
        out[k] = out.get(k, 0.0) + sign * c
    return {k: c for k, c in out.items() if c != 0.0}


def _multiply(a: Terms, b: Terms) -> Terms:
    out: Terms = {}
    for ka, ca in a.items():
        for kb, cb in b.items():
            k = tuple(x + y for x, y in zip(ka, kb, strict=True))
            out[k] = out.get(k, 0.0) + ca * cb
    return {k: c for k, c in out.items() if c != 0.0}


def _power(a: Terms, n: int, size: int) -> Terms:
    out: Terms = {(0,) * size: 1.0}
    for _ in range(n):
        out = _multiply(out, a)
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


def _split_polynomial(terms: Terms, variables: Sequence[str], parameters: Sequence[str],
                      where: str, what: str) -> tuple[Func, tuple[Func, ...]]:
    n_vars = len(variables)
    parts: list[Terms] = [{} for _ in range(len(parameters) + 1)]
    for key, coefficient in terms.items():
        powers = key[n_vars:]
        if sum(powers) > 1:
            involved = [p for p, e in zip(parameters, powers, strict=True) if e]
            term = Polynomial.from_terms({key: coefficient}, [*variables, *parameters]).text()
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
