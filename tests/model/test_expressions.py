"""The evaluable forms of a function (polynomials and sympy expressions), checked against
numpy by hand: values, derivatives, velocity degrees, combinations and stacks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy

from hamid.model.expressions import Func, Polynomial, Symbolic
from hamid.model.parsing import parse, split_linear, to_sympy

X, Y = (sympy.Symbol(n, real=True) for n in ("x", "y"))
RNG_SEED = 20070101


def _states(n_vars: int, n: int = 40, seed: int = RNG_SEED) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.5, 1.5, size=(n, n_vars))


def _split(text: str, variables: list[str], parameters: list[str]):
    return split_linear(parse(text, [*variables, *parameters]), variables, parameters)


# --- the polynomial form ----------------------------------------------------------------

def test_duffing_split_is_polynomial_with_hand_columns():
    E0, (phi_k, phi_k3) = _split("v**2/2 + k*x**2/2 + k3*x**4/4", ["x", "v"], ["k", "k3"])
    S = _states(2)
    x, v = S[:, 0], S[:, 1]
    assert all(isinstance(f, Polynomial) for f in (E0, phi_k, phi_k3))
    np.testing.assert_allclose(E0(S), v**2 / 2, rtol=1e-14)
    np.testing.assert_allclose(phi_k(S), x**2 / 2, rtol=1e-14)
    np.testing.assert_allclose(phi_k3(S), x**4 / 4, rtol=1e-14)


def test_polynomial_expands_products_and_powers():
    text = "v**2/2 + k*(x - 2*y)**3 + g*(x + y + 1)**4/3 + pi*x*y"
    E0, (phi_k, phi_g) = _split(text, ["x", "y", "v"], ["k", "g"])
    S = _states(3)
    x, y, v = S.T
    assert isinstance(phi_g, Polynomial)
    np.testing.assert_allclose(E0(S), v**2 / 2 + np.pi * x * y, rtol=1e-13)
    np.testing.assert_allclose(phi_k(S), (x - 2 * y) ** 3, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(phi_g(S), (x + y + 1) ** 4 / 3, rtol=1e-12, atol=1e-12)


def test_polynomial_evaluates_on_any_leading_shape():
    p = Polynomial(("x", "y"), np.array([[2, 1], [0, 3], [0, 0]]), np.array([1.5, -2.0, 0.25]))
    S = np.random.default_rng(1).normal(size=(3, 4, 2))
    x, y = S[..., 0], S[..., 1]
    got = p(S)
    assert got.shape == (3, 4)
    np.testing.assert_allclose(got, 1.5 * x**2 * y - 2 * y**3 + 0.25, rtol=1e-13)


def test_polynomial_diff_equals_hand_derivative():
    p = Polynomial(("x", "y", "v"), np.array([[2, 1, 0], [0, 3, 0], [1, 0, 2], [0, 0, 0]]),
                   np.array([1.5, -2.0, 0.5, 7.0]))
    S = _states(3)
    x, y, v = S.T
    np.testing.assert_allclose(p.diff("x")(S), 3 * x * y + 0.5 * v**2, rtol=1e-13)
    np.testing.assert_allclose(p.diff("y")(S), 1.5 * x**2 - 6 * y**2, rtol=1e-13)
    np.testing.assert_allclose(p.diff("v")(S), x * v, rtol=1e-13)
    np.testing.assert_allclose(p.diff("x").diff("x")(S), 3 * y, rtol=1e-13)
    assert p.diff("x").diff("x").diff("x").is_zero()
    np.testing.assert_array_equal(p.diff("x").diff("x").diff("x")(S), np.zeros(len(S)))


def test_velocity_degrees_split_the_polynomial():
    E0, _ = _split("v**2*(1 + x**2)/2 + 3*x*v + w*v**3 + x**2 + 3 + k*x", ["x", "w", "v"],
                   ["k"])
    degrees = E0.velocity_degrees(["v"])
    assert sorted(degrees) == [0, 1, 2, 3]
    S = _states(3)
    x, w, v = S.T
    np.testing.assert_allclose(degrees[0](S), x**2 + 3, rtol=1e-13)
    np.testing.assert_allclose(degrees[1](S), 3 * x * v, rtol=1e-13)
    np.testing.assert_allclose(degrees[2](S), v**2 * (1 + x**2) / 2, rtol=1e-13)
    np.testing.assert_allclose(degrees[3](S), w * v**3, rtol=1e-13)


def test_velocity_degrees_over_several_velocities():
    p = Polynomial(("q", "a", "b"), np.array([[1, 1, 1], [0, 2, 0], [2, 0, 0], [0, 0, 1]]),
                   np.array([2.0, 0.5, -1.0, 4.0]))
    degrees = p.velocity_degrees(["a", "b"])
    S = _states(3)
    q, a, b = S.T
    assert sorted(degrees) == [0, 1, 2]
    np.testing.assert_allclose(degrees[0](S), -(q**2), rtol=1e-13)
    np.testing.assert_allclose(degrees[1](S), 4 * b, rtol=1e-13)
    np.testing.assert_allclose(degrees[2](S), 2 * q * a * b + 0.5 * a**2, rtol=1e-13)


def test_combine_polynomials():
    p1 = Polynomial(("x", "v"), np.array([[2, 0], [0, 2]]), np.array([1.0, 0.5]))
    p2 = Polynomial(("x", "v"), np.array([[2, 0], [1, 0]]), np.array([3.0, -1.0]))
    S = _states(2)
    x, v = S.T
    both = Func.combine([p1, p2], [2.0, -1.0])
    assert isinstance(both, Polynomial)
    np.testing.assert_allclose(both(S), -(x**2) + v**2 + x, rtol=1e-13, atol=1e-15)
    assert Func.combine([p1, p1], [1.0, -1.0]).is_zero()


def test_combine_symbolic():
    s1 = Symbolic(("x", "v"), sympy.cos(X))
    s2 = Symbolic(("x", "v"), sympy.Symbol("v", real=True) ** 2)
    S = _states(2)
    x, v = S.T
    np.testing.assert_allclose(Func.combine([s1, s2], [-2.0, 0.5])(S),
                               -2 * np.cos(x) + 0.5 * v**2, rtol=1e-13)


def test_combine_rejects_mixed_kinds():
    p = Polynomial(("x",), np.array([[2]]), np.array([1.0]))
    s = Symbolic(("x",), sympy.cos(X))
    with pytest.raises(TypeError, match="different kinds"):
        Func.combine([p, s], [1.0, 1.0])


def test_polynomial_text_reads_back_as_the_same_function():
    p = Polynomial(("x", "y"), np.array([[2, 1], [0, 3], [1, 0], [0, 0]]),
                   np.array([1.5, -2.0, 1.0, 0.25]))
    back = to_sympy(parse(p.text(), ["x", "y"]))
    want = sympy.Float(1.5) * X**2 * Y - 2 * Y**3 + X + sympy.Float(0.25)
    assert sympy.simplify(back - want) == 0


# --- the symbolic form ------------------------------------------------------------------

def test_pendulum_split_is_symbolic_with_hand_columns():
    E0, (phi,) = _split("v**2/2 - K*cos(x)", ["x", "v"], ["K"])
    S = _states(2)
    x, v = S.T
    assert isinstance(phi, Symbolic)
    np.testing.assert_allclose(E0(S), v**2 / 2, rtol=1e-14)
    np.testing.assert_allclose(phi(S), -np.cos(x), rtol=1e-14)
    np.testing.assert_allclose(phi.diff("x")(S), np.sin(x), rtol=1e-14)
    np.testing.assert_array_equal(phi.diff("v")(S), np.zeros(len(S)))


def test_spec_example_energy_splits_into_hand_columns():
    text = "(vx**2 + vy**2)/2 + k*(x**2 + y**2)/2 - kL*sqrt(x**2 + y**2) + g*y"
    E0, (phi_k, phi_kL, phi_g) = _split(text, ["x", "y", "vx", "vy"], ["k", "kL", "g"])
    S = _states(4)
    x, y, vx, vy = S.T
    np.testing.assert_allclose(E0(S), (vx**2 + vy**2) / 2, rtol=1e-14)
    np.testing.assert_allclose(phi_k(S), (x**2 + y**2) / 2, rtol=1e-14)
    np.testing.assert_allclose(phi_kL(S), -np.sqrt(x**2 + y**2), rtol=1e-14)
    np.testing.assert_allclose(phi_g(S), y, rtol=1e-14)


def test_symbolic_terms_collect_per_parameter():
    text = "v**2/2 + a*exp(x)*(1 + x) - a*log(2 + x**2) + 3*b*tanh(x)/x + abs(v)*sin(x)"
    E0, (phi_a, phi_b) = _split(text, ["x", "v"], ["a", "b"])
    S = _states(2)
    x, v = S.T
    np.testing.assert_allclose(E0(S), v**2 / 2 + np.abs(v) * np.sin(x), rtol=1e-13)
    np.testing.assert_allclose(phi_a(S), np.exp(x) * (1 + x) - np.log(2 + x**2), rtol=1e-13)
    np.testing.assert_allclose(phi_b(S), 3 * np.tanh(x) / x, rtol=1e-13)


def test_symbolic_constant_column_broadcasts():
    _, (phi,) = _split("v**2/2 + k*(sin(x)**2 + cos(x)**2)", ["x", "v"], ["k"])
    S = _states(2)
    np.testing.assert_allclose(phi(S), np.ones(len(S)), rtol=1e-14)


def test_symbolic_velocity_degrees():
    s = Symbolic(("x", "v"), sympy.Symbol("v", real=True) ** 2 * sympy.cos(X) / 2
                 + sympy.sin(X))
    degrees = s.velocity_degrees(["v"])
    S = _states(2)
    x, v = S.T
    assert sorted(degrees) == [0, 2]
    np.testing.assert_allclose(degrees[0](S), np.sin(x), rtol=1e-14)
    np.testing.assert_allclose(degrees[2](S), v**2 * np.cos(x) / 2, rtol=1e-14)
    assert Symbolic(("x", "v"), sympy.cos(sympy.Symbol("v", real=True))).velocity_degrees(
        ["v"]) is None


def test_moderate_expansion_is_exact():
    _, (phi,) = _split("v**2/2 + k*(x + v + 1)**12", ["x", "v"], ["k"])
    S = _states(2, seed=5) / 3
    x, v = S.T
    np.testing.assert_allclose(phi(S), (x + v + 1) ** 12, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize(("text", "zero"), [
    ("(x + 1)**2 - x**2 - 2*x - 1", True),
    ("sin(x)**2 + cos(x)**2 - 1", True),
    ("sqrt(x**2) - abs(x)", True),
    ("exp(log(y + 5)) - y - 5", True),
    ("abs(x) - x", False),           # zero for x > 0 only
    ("sqrt(x**2 + y**2)", False),
    ("1e-12*x", False),              # small is not zero
    ("(sin(x) + cos(x) + tanh(x) + exp(x) + x)**4 - (sin(x) + cos(x) + tanh(x) + exp(x) + x)**4",
     True),
])
def test_symbolic_zero_is_decided_at_points(text, zero):
    symbolic = Symbolic(("x", "y"), to_sympy(parse(text, ["x", "y"])))
    assert isinstance(symbolic.expression, sympy.Expr)
    assert symbolic.is_zero() is zero


def test_a_slow_to_simplify_energy_fits_at_once(clean_records):
    """sympy.simplify took 50 s on this energy, and its 4th power ran past 300 s (it
    now takes a second: a hang here would show as the suite's own)."""
    import hamid
    from hamid.model.models import model_from_expression

    model = model_from_expression(
        "m", "v**2/2 + k*x**2/2 + k3*(sin(x)+cos(x)+tanh(x)+exp(x)+x)**4", ["x"], ["v"])
    result = hamid.fit(clean_records["duffing"], model, method="energy")
    assert set(result.estimates) == {"k", "k3"}
    assert all(np.isfinite(list(result.estimates.values())))


@pytest.mark.parametrize("text", ["x**2*y/3 - 0.7*x*y**3 + 2.5*y + 1.25",      # polynomial
                                  "cos(x)*y**2 + exp(y)/7"])                     # symbolic
def test_a_stack_combined_state_by_state_sums_the_functions_with_each_states_weights(text):
    """Each state's own linear combination of the functions, checked against calling
    each function at each state alone."""
    E0, _ = _split(text, ["x", "y"], [])
    funcs = [E0.diff("x"), E0.diff("y"), E0]
    assert isinstance(E0, Polynomial if "cos" not in text else Symbolic)
    states = _states(2, n=7)
    K = np.random.default_rng(3).normal(size=(2, len(funcs), len(states)))
    combined = Func.stack(funcs).combined(K)(states.T)
    expected = np.array([[sum(K[g, k, j] * float(f(states[j])) for k, f in enumerate(funcs))
                          for j in range(len(states))] for g in range(2)])
    np.testing.assert_allclose(combined, expected, rtol=1e-13, atol=1e-13)


# --- widened to more variables ----------------------------------------------------------

# x = 0.7, v = -1.3 beside inputs (u1, u2) of several values, which must not matter
_WIDE = np.array([[0.7, -1.3, 0.0, 0.0], [0.7, -1.3, 2.5, -4.0], [0.7, -1.3, -1e3, 7.0]])


@pytest.mark.parametrize("kind", ["polynomial", "symbolic"])
def test_a_function_over_more_variables_is_the_same_function_of_its_own(kind):
    """`over` appends variables the function does not depend on: its value and its
    derivatives in x and v are those of the original, written out by hand at (0.7, -1.3),
    whatever the added inputs, and its derivatives in those are zero."""
    x, v = 0.7, -1.3
    if kind == "polynomial":   # 1.5 x**2 v - 2 v**2 + 0.5 x + 3
        f = Polynomial(("x", "v"), np.array([[2, 1], [0, 2], [1, 0], [0, 0]]),
                       np.array([1.5, -2.0, 0.5, 3.0]))
        value, by_x, by_v = -0.9555 - 3.38 + 0.35 + 3.0, 3 * x * v + 0.5, 1.5 * x**2 - 4 * v
    else:                      # v**2 cos(x)/2 + v sin(x)
        V = sympy.Symbol("v", real=True)
        f = Symbolic(("x", "v"), V**2 * sympy.cos(X) / 2 + V * sympy.sin(X))
        value = v**2 * math.cos(x) / 2 + v * math.sin(x)
        by_x = -(v**2) * math.sin(x) / 2 + v * math.cos(x)
        by_v = v * math.cos(x) + math.sin(x)
    wide = f.over(("x", "v", "u1", "u2"))
    assert type(wide) is type(f) and wide.variables == ("x", "v", "u1", "u2")
    for widened, own, want in [(wide, f, value), (wide.diff("x"), f.diff("x"), by_x),
                               (wide.diff("v"), f.diff("v"), by_v)]:
        np.testing.assert_allclose(widened(_WIDE), [want] * 3, rtol=1e-13)
        np.testing.assert_allclose(own(_WIDE[:, :2]), [want] * 3, rtol=1e-13)
    for u in ("u1", "u2"):
        assert wide.diff(u).is_zero()
        np.testing.assert_allclose(wide.diff(u)(_WIDE), np.zeros(3), atol=1e-15)


def test_a_widened_function_stacks_with_a_function_of_the_inputs():
    """The reason for `over`: a function of the state and one of the state and inputs,
    evaluated together (x v**2 widened, and x u beside it, at the rows of _WIDE)."""
    f = Polynomial(("x", "v"), np.array([[1, 2]]), np.array([1.0])).over(("x", "v", "u1", "u2"))
    g = Polynomial(("x", "v", "u1", "u2"), np.array([[1, 0, 1, 0]]), np.array([1.0]))
    got = Func.stack([f, g])(_WIDE.T)
    np.testing.assert_allclose(got[0], [0.7 * 1.69] * 3, rtol=1e-13)
    np.testing.assert_allclose(got[1], [0.0, 0.7 * 2.5, -700.0], rtol=1e-13, atol=1e-15)
