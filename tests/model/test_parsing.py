"""The safe parser: hostile text refused naming the piece, the allowed forms built as sympy
builds them by hand, and energies not linear in their parameters refused naming the term."""

from __future__ import annotations

import ast
import builtins
import cmath
import operator
import os
import re

import pytest
import sympy
from helpers import SAFE_NODES, parsed_running_nothing
from hypothesis import given, settings
from hypothesis import strategies as st

from hamid.errors import ModelError
from hamid.model.parsing import (
    FUNCTIONS,
    MAX_LENGTH,
    parse,
    split_linear,
    symbols_in_order,
    to_sympy,
)

X, Y, Z, K = (sympy.Symbol(n, real=True) for n in ("x", "y", "z", "k"))


def _split(text: str, variables: list[str], parameters: list[str]):
    return split_linear(parse(text, [*variables, *parameters]), variables, parameters)


def _same(a: sympy.Expr, b: sympy.Expr) -> bool:
    """Structurally equal, or equal in value at a few points (complex where need be)."""
    if a == b:
        return True
    points = ({X: 0.37, Y: -1.21, Z: 2.3, K: 0.83}, {X: -0.6, Y: 0.45, Z: 0.7, K: -1.9},
              {X: 1.7, Y: 2.2, Z: -0.3, K: 0.11})
    for point in points:
        values = []
        for e in (a, b):
            v = sympy.N(e.subs(point), 30)
            try:
                values.append(complex(v))
            except TypeError:  # zoo, nan
                values.append(None)
        va, vb = values
        if va is None or vb is None:
            if va is not vb:
                return False
        elif not cmath.isclose(va, vb, rel_tol=1e-9, abs_tol=1e-12):
            return False
    return True


# --- hostile and malformed text ---------------------------------------------------------

HOSTILE = [
    ("__import__('os').system('echo hacked')",
     r"only the functions .* may be called: \"__import__\('os'\)\.system\('echo hacked'\)\""),
    ("().__class__", r"attribute access is not allowed: '\(\)\.__class__'"),
    ("x.real", r"attribute access is not allowed: 'x\.real'"),
    ("x.__class__.__bases__", r"attribute access is not allowed: 'x\.__class__\.__bases__'"),
    ("lambda: 1", r"lambda is not allowed: 'lambda: 1'"),
    ("(lambda: 1)()", r"may be called: '\(lambda: 1\)\(\)'"),
    ("[x for x in y]", r"a comprehension is not allowed: '\[x for x in y\]'"),
    ("(x for x in y)", r"a comprehension is not allowed: '\(x for x in y\)'"),
    ("{x: 1}", r"dict is not allowed: '\{x: 1\}'"),
    ("{x}", r"set is not allowed: '\{x\}'"),
    ("[x]", r"list is not allowed: '\[x\]'"),
    ("(x, y)", r"tuple is not allowed: '\(x, y\)'"),
    ("x if y else z", r"a conditional is not allowed: 'x if y else z'"),
    ("x[0]", r"indexing is not allowed: 'x\[0\]'"),
    ("open('f')", r"unknown function 'open' in \"open\('f'\)\""),
    ("eval('1')", r"unknown function 'eval' in \"eval\('1'\)\""),
    ("getattr(x, 'y')", r"unknown function 'getattr' in \"getattr\(x, 'y'\)\""),
    ("x(y)", r"unknown function 'x' in 'x\(y\)'"),
    ("pi(x)", r"unknown function 'pi' in 'pi\(x\)'"),
    ("sin(x)(y)", r"may be called: 'sin\(x\)\(y\)'"),
    ("x**10**10", r"the exponent '10\*\*10' must be a number"),
    ("x**y", r"the exponent 'y' must be a number"),
    ("x**(1/0)", r"the exponent '1/0' must be a number"),
    ("x**65", r"the exponent '65' is too large"),
    ("x**-65", r"the exponent '-65' is too large"),
    ("x**1e400", r"the exponent '1e400' is too large"),
    ("x**" + "9" * 400, r"the exponent '9{400}' is too large"),
    ("x == y", r"a comparison is not allowed: 'x == y'"),
    ("x < y", r"a comparison is not allowed: 'x < y'"),
    ("x and y", r"a boolean operator is not allowed: 'x and y'"),
    ("not x", r"operator not allowed in 'not x'"),
    ("~x", r"operator not allowed in '~x'"),
    ("x // y", r"operator not allowed in 'x // y'"),
    ("x % y", r"operator not allowed in 'x % y'"),
    ("x @ y", r"operator not allowed in 'x @ y'"),
    ("x ^ y", r"operator not allowed in 'x \^ y'"),
    ("'text'", r"only numbers may appear as constants: \"'text'\""),
    ("b'bytes'", r"only numbers may appear as constants: \"b'bytes'\""),
    ("f'{x}'", r"joinedstr is not allowed: \"f'\{x\}'\""),
    ("1j", r"only numbers may appear as constants: '1j'"),
    ("True", r"only numbers may appear as constants: 'True'"),
    ("None", r"only numbers may appear as constants: 'None'"),
    ("...", r"only numbers may appear as constants: '\.\.\.'"),
    ("1e400 * x", r"the number '1e400' is too large"),
    ("9" * 400 + " * x", r"the number '9{400}' is too large"),
    ("x := 1", r"cannot parse 'x := 1'"),
    ("(x := 1)", r"an assignment is not allowed: 'x := 1'"),
    ("x; y", r"cannot parse 'x; y'"),
    ("import os", r"cannot parse 'import os'"),
    ("sin", r"'sin' is a function and needs an argument"),
    ("x + abs", r"'abs' is a function and needs an argument"),
    ("sin(x, y)", r"sin\(\) takes exactly one argument: 'sin\(x, y\)'"),
    ("sin(x=1)", r"sin\(\) takes exactly one argument: 'sin\(x=1\)'"),
    ("sin(x, y=1)", r"sin\(\) takes exactly one argument: 'sin\(x, y=1\)'"),
    ("cos()", r"cos\(\) takes exactly one argument: 'cos\(\)'"),
    ("sin(*x)", r"a starred argument is not allowed: '\*x'"),
    ("(x + 1", r"cannot parse '\(x \+ 1': '\(' was never closed"),
    ("x + 1)", r"cannot parse 'x \+ 1\)': unmatched '\)'"),
    ("x +", r"cannot parse 'x \+'"),
    ("", r"the expression is empty"),
    ("   ", r"the expression is empty"),
    ("x" * 20_000, rf"the expression is 20000 characters long \(at most {MAX_LENGTH}\)"),
    ("(" * 500 + "x" + ")" * 500, r"cannot parse '\(\(\(\("),
    ("-" * 2000 + "x", r"nested \d+ levels deep \(at most \d+\)|cannot parse '----"),
    ("+".join(["x"] * 1500), r"nested \d+ levels deep \(at most \d+\)|cannot parse 'x\+x\+"),
]


@pytest.mark.parametrize(("text", "message"), HOSTILE, ids=[t[:30] for t, _ in HOSTILE])
def test_hostile_text_is_rejected_naming_the_piece(text, message):
    with pytest.raises(ModelError, match=message):
        parse(text, None, where="model.toml: energy")


@pytest.mark.parametrize(("text", "message"), HOSTILE[:12], ids=[t[:30] for t, _ in HOSTILE[:12]])
def test_messages_start_with_where(text, message):
    with pytest.raises(ModelError, match=r"^sys\.toml: energy: "):
        parse(text, None, where="sys.toml: energy")


def test_nothing_runs_while_parsing_hostile_text(tmp_path, monkeypatch):
    sentinel = tmp_path / "hacked"
    calls = []
    monkeypatch.setattr(os, "system", lambda *a: calls.append(("system", a)) or 0)
    monkeypatch.setattr(builtins, "eval", lambda *a, **k: calls.append(("eval", a)))
    monkeypatch.setattr(builtins, "exec", lambda *a, **k: calls.append(("exec", a)))
    texts = [f"__import__('os').system('touch {sentinel}')",
             f"open('{sentinel}', 'w').write('x')",
             f"eval(\"__import__('os').system('touch {sentinel}')\")",
             f"(lambda: __import__('os').system('touch {sentinel}'))()"]
    for text in texts:
        with pytest.raises(ModelError, match="function|lambda"):
            parse(text, None)
    assert not sentinel.exists()
    assert calls == []


def test_unknown_symbol_is_named_when_names_are_declared():
    with pytest.raises(ModelError, match=r"energy: unknown symbol 'w'"):
        parse("x**2 + w*x", ["x"])


IDENTIFIERS = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,8}", fullmatch=True).filter(
    lambda n: n not in {"x", "pi", *FUNCTIONS} and n.isidentifier())


@settings(max_examples=50, deadline=None)
@given(IDENTIFIERS)
def test_every_undeclared_name_is_rejected(name):
    """Keywords fail to parse; every other name is an unknown symbol, named in the message."""
    import keyword

    message = "cannot parse" if keyword.iskeyword(name) else f"unknown symbol {name!r}"
    if name in {"True", "False", "None"}:
        message = "only numbers may appear"
    with pytest.raises(ModelError, match=re.escape(message)):
        parse(f"x + 2*{name}", ["x"])


# --- accepted forms ---------------------------------------------------------------------

ACCEPTED = [
    ("sqrt(x)", sympy.sqrt(X)),
    ("exp(x)", sympy.exp(X)),
    ("log(x)", sympy.log(X)),
    ("sin(x)", sympy.sin(X)),
    ("cos(x)", sympy.cos(X)),
    ("tan(x)", sympy.tan(X)),
    ("sinh(x)", sympy.sinh(X)),
    ("cosh(x)", sympy.cosh(X)),
    ("tanh(x)", sympy.tanh(X)),
    ("abs(x)", sympy.Abs(X)),
    ("pi", sympy.pi),
    ("pi*x**2/4", sympy.pi * X**2 / 4),
    ("-x", -X),
    ("+x", X),
    ("-(-x)", X),
    ("x**(1/2)", sympy.sqrt(X)),
    ("x**-1", 1 / X),
    ("x**(-1/2)", 1 / sympy.sqrt(X)),
    ("x**(2/3)", X ** sympy.Rational(2, 3)),
    ("x**0", sympy.Integer(1)),
    ("x**2.0", X**2),
    ("x**64", X**64),
    ("1.5*x - y/3", sympy.Float(1.5) * X - Y / 3),
    ("2e-3*x", sympy.Float(0.002) * X),
    ("(x + y)**2", (X + Y) ** 2),
    ("x - y - z", X - Y - Z),
    ("x/y/z", X / (Y * Z)),
    ("sin(cos(x))**2 + exp(-y)", sympy.sin(sympy.cos(X)) ** 2 + sympy.exp(-Y)),
    ("(vx**2 + vy**2)/2 - kL*sqrt(x**2 + y**2)",
     (sympy.Symbol("vx", real=True) ** 2 + sympy.Symbol("vy", real=True) ** 2) / 2
     - sympy.Symbol("kL", real=True) * sympy.sqrt(X**2 + Y**2)),
    ("  x  ", X),
    ("(" * 50 + "x" + ")" * 50, X),
]


@pytest.mark.parametrize(("text", "want"), ACCEPTED, ids=[t[:30] for t, _ in ACCEPTED])
def test_allowed_forms_parse_to_the_sympy_expression(text, want):
    got = to_sympy(parse(text, ["x", "y", "z", "vx", "vy", "kL"]))
    assert sympy.simplify(got - want) == 0
    assert _same(got, want)


def test_symbols_are_real():
    """Symbols are real, so sqrt(x**2) is |x| and not a complex branch."""
    assert to_sympy(parse("sqrt(x**2)", ["x"])) == sympy.Abs(X)


def test_every_function_is_covered():
    tested = {t.split("(")[0] for t, _ in ACCEPTED if "(" in t}
    assert set(FUNCTIONS) <= tested


@pytest.mark.parametrize(("text", "want"), [
    ("b*x + a*y**2 + b*z + sin(c)", ["b", "x", "a", "y", "z", "c"]),
    ("v**2/2 + k3*x**4/4 + k*x**2/2", ["v", "k3", "x", "k"]),
    ("pi*x + sqrt(q) + exp(q)", ["x", "q"]),
])
def test_symbols_in_order_of_first_appearance(text, want):
    assert symbols_in_order(parse(text, None)) == want


# --- grammar-based property -------------------------------------------------------------

_SYMPY_FUNCTIONS = {"sqrt": sympy.sqrt, "exp": sympy.exp, "log": sympy.log, "sin": sympy.sin,
                    "cos": sympy.cos, "tan": sympy.tan, "sinh": sympy.sinh,
                    "cosh": sympy.cosh, "tanh": sympy.tanh, "abs": sympy.Abs}
_BINARY = {"+": operator.add, "-": operator.sub, "*": operator.mul, "/": operator.truediv}

_LEAVES = st.one_of(
    st.sampled_from([("x", X), ("y", Y), ("k", K)]),
    st.integers(0, 9).map(lambda i: (str(i), sympy.Integer(i))),
    st.sampled_from(["0.5", "1.25", "2.5", "3e-2"]).map(lambda s: (s, sympy.Float(s))),
    st.just(("pi", sympy.pi)),
)
_EXPONENTS = st.sampled_from([("2", sympy.Integer(2)), ("3", sympy.Integer(3)),
                              ("-1", sympy.Integer(-1)), ("(1/2)", sympy.Rational(1, 2)),
                              ("(-3/2)", sympy.Rational(-3, 2)), ("2.0", sympy.Float(2.0))])


def _extend(children):
    binary = st.tuples(children, st.sampled_from(sorted(_BINARY)), children).map(
        lambda t: (f"({t[0][0]}) {t[1]} ({t[2][0]})", _BINARY[t[1]](t[0][1], t[2][1])))
    unary = children.map(lambda c: (f"-({c[0]})", -c[1]))
    call = st.tuples(st.sampled_from(FUNCTIONS), children).map(
        lambda t: (f"{t[0]}({t[1][0]})", _SYMPY_FUNCTIONS[t[0]](t[1][1])))
    power = st.tuples(children, _EXPONENTS).map(
        lambda t: (f"({t[0][0]})**{t[1][0]}", t[0][1] ** t[1][1]))
    return st.one_of(binary, unary, call, power)


EXPRESSIONS = st.recursive(_LEAVES, _extend, max_leaves=8)


@settings(max_examples=50, deadline=None)
@given(EXPRESSIONS)
def test_parsed_expression_equals_the_one_built_alongside(pair):
    text, want = pair
    got = to_sympy(parse(text, ["x", "y", "k"]))
    assert _same(got, want), (text, got, want)


_FORBIDDEN_TOKENS = [".", "[", "]", "[0]", "lambda", "lambda: ", "__", "import", "'", '"',
                     "'x'", ".__class__", "__import__('os')", " if x else ", ",", "=", ";",
                     "__builtins__", "os.system('echo hacked')"]


@settings(max_examples=50, deadline=None)
@given(EXPRESSIONS, st.sampled_from(_FORBIDDEN_TOKENS), st.data())
def test_forbidden_tokens_are_rejected_or_harmless(pair, token, data):
    text = pair[0]
    at = data.draw(st.integers(0, len(text)), label="at")
    mutated = text[:at] + token + text[at:]
    tree = parsed_running_nothing(mutated, ["x", "y", "k"])
    if tree is not None:
        nodes = list(ast.walk(tree))
        assert all(isinstance(n, SAFE_NODES) for n in nodes), mutated
        names = {n.id for n in nodes if isinstance(n, ast.Name)}
        assert names <= {"x", "y", "k", "pi", *FUNCTIONS}, mutated
        assert all(isinstance(n.value, int | float) and not isinstance(n.value, bool)
                   for n in nodes if isinstance(n, ast.Constant)), mutated




# --- split_linear errors ----------------------------------------------------------------

NONLINEAR = [
    ("v**2/2 + k*kL*x**2", ["k", "kL"], "(k, kL)", ["x**2", "k", "kL"]),
    ("v**2/2 + k**2*x**2", ["k"], "(k)", ["k**2"]),
    ("v**2/2 + (k + x)**2", ["k"], "(k)", ["k**2"]),
    ("v**2/2 + x**2/k", ["k"], "(k)", ["x**2/k"]),
    ("v**2/2 + exp(k*x)", ["k"], "(k)", ["exp(k*x)"]),
    ("v**2/2 + sin(k)*x", ["k"], "(k)", ["sin(k)"]),
    ("v**2/2 + sqrt(k)*x**2", ["k"], "(k)", ["sqrt(k)"]),
    ("v**2/2 + k*x**2 + k*kL*cos(x)", ["k", "kL"], "(k, kL)", ["cos(x)"]),
]


@pytest.mark.parametrize(("text", "parameters", "involved", "pieces"), NONLINEAR,
                         ids=[t for t, *_ in NONLINEAR])
def test_nonlinear_energy_is_rejected_naming_term_and_parameters(text, parameters, involved,
                                                                  pieces):
    with pytest.raises(ModelError, match=r"energy term '[^']+' is not linear in the "
                       + re.escape(f"parameters {involved}")) as info:
        _split(text, ["x", "v"], parameters)
    term = re.search(r"term '([^']+)'", str(info.value)).group(1)
    for piece in pieces:
        assert piece in term


@pytest.mark.parametrize("text", ["k*x**2/2 + m*v**2/2", "m*v**2/2 - k*cos(x)"])
def test_energy_without_parameter_free_part_splits_to_a_zero_part(text):
    """Allowed here: the fit takes the scale from a fixed parameter (`Unknowns.of`)."""
    E0, phi = _split(text, ["x", "v"], ["m", "k"])
    assert E0.is_zero() and not any(f.is_zero() for f in phi)


@pytest.mark.parametrize("text", ["v**2/2 + k*x**2", "v**2/2 + k*x**2 + g*x - g*x",
                                  "v**2/2 - k*cos(x)", "v**2/2 - k*cos(x) + 0*g"])
def test_declared_parameter_that_does_not_appear_is_rejected(text):
    with pytest.raises(ModelError, match=r"parameter 'g' does not appear in the energy"):
        _split(text, ["x", "v"], ["k", "g"])


@pytest.mark.parametrize("text", ["v**2/2 + k*x/0", "v**2/2 + k*x/(x - x)",
                                  "v**2/2 + k*x + 1/(2 - 2)"])
def test_division_by_zero_is_rejected(text):
    with pytest.raises(ModelError, match=r"energy term '[^']*zoo[^']*' is not finite"):
        _split(text, ["x", "v"], ["k"])


@pytest.mark.parametrize(("text", "piece"), [
    ("v**2/2 + k*((x + v + 1)**64)**64", "((x + v + 1) ** 64) ** 64"),
    ("v**2/2 + k*(x + v + 1)**64*(x - v)**64", "k * (x + v + 1) ** 64 * (x - v) ** 64"),
    ("v**2/2 + k*x**64*x**64*x**64*x**64*x**64", "k * x ** 64 * x ** 64 * x ** 64 * x ** 64"),
    ("v**2/2 + k*cos((x + v + 1)**64*(x + v)**64) + sin(x)",
     "(x + v + 1) ** 64 * (x + v) ** 64"),
])
def test_energy_that_would_expand_enormously_is_rejected(text, piece):
    """Small text must not exhaust memory or time by expanding; the check names the piece."""
    with pytest.raises(ModelError, match=re.escape(repr(piece)) + " expands to too many"):
        _split(text, ["x", "v"], ["k"])


