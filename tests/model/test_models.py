"""Models: built-ins against the README's table, the poly family, expression models,
natural split."""

from __future__ import annotations

import re

import numpy as np
import pytest

from hamid.errors import ModelError
from hamid.model.models import (
    BUILTINS,
    Lagrangian,
    builtin_model,
    model_from_expression,
    model_from_spec,
)


def _states(n_vars: int, n: int = 30, seed: int = 7) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.5, 1.5, size=(n, n_vars))


# --- built-in models against the README's table ---------------------------------------------
# Each entry: coordinates, velocities, parameters, E0 and the phi columns, all written by
# hand from the README's table as functions of the named state columns.

def _peng_columns(u1, u2, v1, v2):
    return ((v1**2 + v2**2) / 2,
            [u1**2 / 2, u2**2 / 2, -(u1**3) / 3, -(u1**2) * u2 / 2, -u1 * u2**2, -(u2**3) / 3])


def _duffing_columns(x, v):
    return v**2 / 2, [x**2 / 2, x**4 / 4]


def _henon_columns(x, y, vx, vy):
    return (vx**2 + vy**2) / 2, [x**2 / 2, y**2 / 2, x**2 * y, y**3]


BUILTIN_TABLE = {
    "peng-quadratic": (("u1", "u2"), ("v1", "v2"), ("w1sq", "w2sq", "a1", "a2", "a3", "a6"),
                       _peng_columns),
    "duffing": (("x",), ("v",), ("k", "k3"), _duffing_columns),
    "henon-heiles": (("x", "y"), ("vx", "vy"), ("a", "b", "c", "d"), _henon_columns),
}


def test_the_builtins_are_those_of_spec():
    assert set(BUILTINS) == set(BUILTIN_TABLE)


@pytest.mark.parametrize("name", sorted(BUILTIN_TABLE))
def test_builtin_names_match_spec(name):
    coordinates, velocities, parameters, _ = BUILTIN_TABLE[name]
    model = builtin_model(name)
    assert model.name == name
    assert model.coordinates == coordinates
    assert model.velocities == velocities
    assert model.variables == coordinates + velocities
    assert model.parameters == parameters
    assert model.is_polynomial
    assert model.info() == {"name": name, "energy": BUILTINS[name]["energy"],
                            "coordinates": list(coordinates), "velocities": list(velocities),
                            "parameters": list(parameters), "dissipation": None}


@pytest.mark.parametrize("name", sorted(BUILTIN_TABLE))
def test_builtin_energy_basis_equals_spec_energy(name):
    coordinates, velocities, parameters, columns = BUILTIN_TABLE[name]
    S = _states(len(coordinates) * 2)
    E0_want, phi_want = columns(*S.T)
    E0, Phi = builtin_model(name).energy_basis(S)
    assert Phi.shape == (len(S), len(parameters))
    np.testing.assert_allclose(E0, E0_want, rtol=1e-14)
    np.testing.assert_allclose(Phi, np.column_stack(phi_want), rtol=1e-13, atol=1e-15)


def test_henon_heiles_total_energy_at_the_classic_values():
    S = _states(4)
    x, y, vx, vy = S.T
    want = (vx**2 + vy**2) / 2 + (x**2 + y**2) / 2 + x**2 * y - y**3 / 3
    got = builtin_model("henon-heiles").total_energy(S, [1.0, 1.0, 1.0, -1.0 / 3.0])
    np.testing.assert_allclose(got, want, rtol=1e-13)


# --- the poly:N:D family ----------------------------------------------------------------

def test_poly_2_3_names_and_columns():
    model = builtin_model("poly:2:3")
    assert model.coordinates == ("q1", "q2")
    assert model.velocities == ("v1", "v2")
    assert model.parameters == ("c_2_0", "c_1_1", "c_0_2", "c_3_0", "c_2_1", "c_1_2", "c_0_3")
    S = _states(4)
    q1, q2, v1, v2 = S.T
    E0, Phi = model.energy_basis(S)
    np.testing.assert_allclose(E0, (v1**2 + v2**2) / 2, rtol=1e-14)
    want = np.column_stack([q1**2, q1 * q2, q2**2, q1**3, q1**2 * q2, q1 * q2**2, q2**3])
    np.testing.assert_allclose(Phi, want, rtol=1e-14)


def test_poly_1_4_names_and_columns():
    model = builtin_model("poly:1:4")
    assert (model.coordinates, model.velocities) == (("q1",), ("v1",))
    assert model.parameters == ("c_2", "c_3", "c_4")
    S = _states(2)
    q1, v1 = S.T
    E0, Phi = model.energy_basis(S)
    np.testing.assert_allclose(E0, v1**2 / 2, rtol=1e-14)
    np.testing.assert_allclose(Phi, np.column_stack([q1**2, q1**3, q1**4]), rtol=1e-14)


def test_poly_3_2_names():
    assert builtin_model("poly:3:2").parameters == (
        "c_2_0_0", "c_1_1_0", "c_1_0_1", "c_0_2_0", "c_0_1_1", "c_0_0_2")


@pytest.mark.parametrize("name", ["poly:0:3", "poly:2:1", "poly:x", "poly:2", "poly:2:3:4",
                                  "poly:", "poly:2:x", "poly:-1:3", "poly:2.5:3"])
def test_bad_poly_names_are_rejected(name):
    with pytest.raises(ModelError, match=re.escape(f"model {name!r}: expected poly:N:D")):
        builtin_model(name)


def test_poly_with_too_many_terms_is_rejected():
    # monomials of degree 2..30 in 2 coordinates: 3 + 4 + ... + 31 = 493
    with pytest.raises(ModelError, match=r"poly:2:30 has 493 terms \(at most 200\)"):
        builtin_model("poly:2:30")


@pytest.mark.parametrize("name", ["nope", "Duffing", "peng", "henon_heiles"])
def test_unknown_model_is_rejected_listing_the_builtins(name):
    with pytest.raises(ModelError, match=re.escape(f"unknown model {name!r}; built-in models: "
                                                   "peng-quadratic, duffing, henon-heiles, "
                                                   "poly:N:D")):
        builtin_model(name)


# --- models from an expression ----------------------------------------------------------

@pytest.mark.parametrize(("energy", "coordinates", "velocities", "want"), [
    ("v**2/2 + k*x**2/2 + k3*x**4/4", ["x"], ["v"], ("k", "k3")),
    ("k3*x**4/4 + v**2/2 + k*x**2/2", ["x"], ["v"], ("k3", "k")),
    ("v**2/2 + kz*x**2 + ka*x**4 + kz*x**3 - m*cos(x) + pi*x", ["x"], ["v"], ("kz", "ka", "m")),
    ("(vx**2 + vy**2)/2 + k*(x**2 + y**2)/2 - kL*sqrt(x**2 + y**2) + g*y", ["x", "y"],
     ["vx", "vy"], ("k", "kL", "g")),
])
def test_default_parameters_in_order_of_appearance(energy, coordinates, velocities, want):
    model = model_from_expression("m", energy, coordinates, velocities)
    assert model.parameters == want


def test_expression_model_basis_equals_hand_columns():
    model = model_from_expression(
        "ring", "(vx**2 + vy**2)/2 + k*(x**2 + y**2)/2 - kL*sqrt(x**2 + y**2) + g*y",
        ["x", "y"], ["vx", "vy"], ["g", "k", "kL"])
    S = _states(4)
    x, y, vx, vy = S.T
    E0, Phi = model.energy_basis(S)
    assert not model.is_polynomial
    np.testing.assert_allclose(E0, (vx**2 + vy**2) / 2, rtol=1e-14)
    want = np.column_stack([y, (x**2 + y**2) / 2, -np.sqrt(x**2 + y**2)])
    np.testing.assert_allclose(Phi, want, rtol=1e-14)


def test_unknown_symbol_is_rejected_when_parameters_are_declared():
    with pytest.raises(ModelError, match=r"^model: energy: unknown symbol 'g'$"):
        model_from_expression("m", "v**2/2 + k*x**2 + g*x", ["x"], ["v"], ["k"])


@pytest.mark.parametrize(("coordinates", "velocities", "parameters", "name"), [
    (["x"], ["v"], ["k", "k"], "k"),
    (["x"], ["x"], ["k"], "x"),
    (["x"], ["v"], ["x"], "x"),
    (["x", "y"], ["v", "v"], ["k"], "v"),
    (["x", "y"], ["vx", "vy"], ["vy"], "vy"),
])
def test_duplicate_names_are_rejected(coordinates, velocities, parameters, name):
    with pytest.raises(ModelError, match=f"the name {name!r} is declared more than once"):
        model_from_expression("m", "v**2/2 + k*x**2", coordinates, velocities, parameters)


@pytest.mark.parametrize(("coordinates", "velocities", "message"), [
    (["x", "y"], ["v"], "2 coordinates but 1 velocities"),
    (["x"], ["v", "w"], "1 coordinates but 2 velocities"),
    ([], [], "'coordinates' must list at least one name"),
])
def test_mismatched_coordinates_and_velocities_are_rejected(coordinates, velocities, message):
    with pytest.raises(ModelError, match=re.escape(message)):
        model_from_expression("m", "v**2/2 + k*x**2", coordinates, velocities, ["k"])


BAD_NAMES = ["sin", "sqrt", "abs", "pi", "lambda", "class", "None", "True", "1x", "x y",
             "x.y", "", "k-1"]


@pytest.mark.parametrize("role", ["coordinate", "velocity", "parameter"])
@pytest.mark.parametrize("bad", BAD_NAMES)
def test_names_that_are_functions_keywords_or_pi_are_rejected(bad, role):
    names = {"coordinate": [bad], "velocity": ["v"], "parameter": ["k"]}
    if role == "velocity":
        names = {"coordinate": ["x"], "velocity": [bad], "parameter": ["k"]}
    elif role == "parameter":
        names = {"coordinate": ["x"], "velocity": ["v"], "parameter": [bad]}
    with pytest.raises(ModelError, match=re.escape(f"{bad!r} cannot be used as a name")):
        model_from_expression("m", "v**2/2 + k*x**2", names["coordinate"], names["velocity"],
                              names["parameter"], where="sys.toml")


@pytest.mark.parametrize(("energy", "message"), [
    ("v**2/2 + x**2", "the energy has no parameters to fit"),
    ("v**2/2 + k*x**2 + sin*x", "'sin' is a function and needs an argument"),
    ("v**2/2 + k*x.real", "attribute access is not allowed: 'x.real'"),
    ("v**2/2 + k*kL*x**2", "energy term 'x**2*k*kL' is not linear in the parameters (k, kL)"),
])
def test_bad_expression_models_are_rejected(energy, message):
    with pytest.raises(ModelError, match=r"^model\.toml: .*" + re.escape(message)):
        model_from_expression("m", energy, ["x"], ["v"], where="model.toml")


# --- natural energies and the Lagrangian ------------------------------------------------

MASS_ENERGY = "(v1**2 + m*v2**2)/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2 + k3*x2**4/4"


def _mass_model():
    return model_from_expression("mass", MASS_ENERGY, ["x1", "x2"], ["v1", "v2"])


def _mass_gradients(x1, x2, v1, v2):
    """L = v1**2/2 + m v2**2/2 - k1 x1**2/2 - k2 (x2 - x1)**2/2 - k3 x2**4/4, by hand.

    Returns [dL/dv_i per part] and [dL/dq_i per part], parts (L0, m, k1, k2, k3).
    """
    zero = np.zeros_like(x1)
    dv = [[v1, zero], [zero, v2], [zero, zero], [zero, zero], [zero, zero]]
    dq = [[zero, zero], [zero, zero], [-x1, zero], [x2 - x1, -(x2 - x1)], [zero, -(x2**3)]]
    return dv, dq


def _duffing_gradients(x, v):
    zero = np.zeros_like(x)
    return [[v], [zero], [zero]], [[zero], [-x], [-(x**3)]]


def _pendulum_gradients(x, v):
    """E = v**2/2 - g*cos(x): V = -g cos(x), L = v**2/2 + g cos(x)."""
    zero = np.zeros_like(x)
    return [[v], [zero]], [[zero], [-np.sin(x)]]


def _varying_mass_gradients(x, v):
    """E = v**2 (1 + g x**2)/2 + k x**2/2: L_g = v**2 x**2/2, L_k = -x**2/2."""
    zero = np.zeros_like(x)
    return [[v], [v * x**2], [zero]], [[zero], [v**2 * x], [-x]]


def _symbolic_mass_gradients(x1, x2, v1, v2):
    """E = (v1**2 + m v2**2)/2 + k x1**2/2 - g cos(x2)."""
    zero = np.zeros_like(x1)
    return ([[v1, zero], [zero, v2], [zero, zero], [zero, zero]],
            [[zero, zero], [zero, zero], [-x1, zero], [zero, -np.sin(x2)]])


NATURAL = {
    "mass": (_mass_model, ("m", "k1", "k2", "k3"), _mass_gradients),
    "duffing": (lambda: builtin_model("duffing"), ("k", "k3"), _duffing_gradients),
    "pendulum": (lambda: model_from_expression("p", "v**2/2 - g*cos(x)", ["x"], ["v"]),
                 ("g",), _pendulum_gradients),
    "varying-mass": (lambda: model_from_expression("vm", "v**2*(1 + g*x**2)/2 + k*x**2/2",
                                                   ["x"], ["v"]),
                     ("g", "k"), _varying_mass_gradients),
    "symbolic-mass": (lambda: model_from_expression(
        "sm", "(v1**2 + m*v2**2)/2 + k*x1**2/2 - g*cos(x2)", ["x1", "x2"], ["v1", "v2"]),
        ("m", "k", "g"), _symbolic_mass_gradients),
}


@pytest.mark.parametrize("name", sorted(BUILTIN_TABLE))
def test_builtins_are_natural(name):
    model = builtin_model(name)
    assert model.is_natural
    assert isinstance(model.lagrangian, Lagrangian)


@pytest.mark.parametrize("case", sorted(NATURAL))
def test_lagrangian_gradients_equal_hand_derivatives(case):
    make, parameters, hand = NATURAL[case]
    model = make()
    assert model.parameters == parameters
    assert model.is_natural
    n_coordinates = len(model.coordinates)
    S = _states(2 * n_coordinates)
    dv_want, dq_want = hand(*S.T)
    dLdv, dLdq = model.lagrangian.gradients(S)
    shape = (len(S), n_coordinates, 1 + len(parameters))
    assert dLdv.shape == shape and dLdq.shape == shape
    for part in range(1 + len(parameters)):
        for i in range(n_coordinates):
            np.testing.assert_allclose(dLdv[:, i, part], dv_want[part][i], rtol=1e-13,
                                       atol=1e-15, err_msg=f"dL/dv{i} part {part}")
            np.testing.assert_allclose(dLdq[:, i, part], dq_want[part][i], rtol=1e-13,
                                       atol=1e-15, err_msg=f"dL/dq{i} part {part}")


def test_lagrangian_gives_the_equation_of_motion():
    """Duffing with theta: d/dt(dL/dv) = dL/dq reads  a = -k x - k3 x**3."""
    theta = np.array([1.0, 1.3, -0.4])  # 1 for the parameter-free part, then k, k3
    S = _states(2)
    x, v = S.T
    dLdv, dLdq = builtin_model("duffing").lagrangian.gradients(S)
    np.testing.assert_allclose(dLdv[:, 0, :] @ theta, v, rtol=1e-14)
    np.testing.assert_allclose(dLdq[:, 0, :] @ theta, -1.3 * x + 0.4 * x**3, rtol=1e-13)


@pytest.mark.parametrize(("energy", "part", "term"), [
    ("v**2/2 + k*x**2 + g*x*v", "the term of 'g'", "x*v"),
    ("v**2/2 + k*x**2 + g*v**3", "the term of 'g'", "v**3"),
    ("v**2/2 + x*v + k*x**2", "the parameter-free part", "x*v"),
    ("v**2/2 + v**4 + k*x**2", "the parameter-free part", "v**4"),
    ("v**2/2 + k*x**2 + g*cos(v)", "the term of 'g'", "cos(v)"),
    ("v**2/2 + x*v + k*cos(x)", "the parameter-free part", "v*x"),
])
def test_energy_that_is_not_natural(energy, part, term):
    model = model_from_expression("odd", energy, ["x"], ["v"])
    assert not model.is_natural
    with pytest.raises(ModelError, match=re.escape(f"model 'odd': {part} of the energy is not "
                                                   "a kinetic energy")
                       + ".*" + re.escape(repr(term))):
        model.lagrangian  # noqa: B018


# --- [model] tables ---------------------------------------------------------------------

def test_spec_builtin_form():
    model = model_from_spec({"builtin": "peng-quadratic"})
    assert model.name == "peng-quadratic"
    assert model.parameters == BUILTIN_TABLE["peng-quadratic"][2]


def test_spec_expression_form():
    spec = {"name": "osc", "coordinates": ["x"], "velocities": ["v"],
            "energy": "v**2/2 + k*x**2/2 - g*cos(x)", "parameters": ["g", "k"]}
    model = model_from_spec(spec)
    assert (model.name, model.coordinates, model.velocities, model.parameters) == (
        "osc", ("x",), ("v",), ("g", "k"))
    S = _states(2)
    x, v = S.T
    E0, Phi = model.energy_basis(S)
    np.testing.assert_allclose(E0, v**2 / 2, rtol=1e-14)
    np.testing.assert_allclose(Phi, np.column_stack([-np.cos(x), x**2 / 2]), rtol=1e-14)


def test_spec_expression_form_default_parameters():
    model = model_from_spec({"coordinates": ["x"], "velocities": ["v"],
                             "energy": "v**2/2 + k3*x**4/4 + k*x**2/2"})
    assert model.parameters == ("k3", "k")


@pytest.mark.parametrize(("key", "suggestion"), [
    ("energie", "energy"), ("parameter", "parameters"), ("coordinate", "coordinates"),
    ("velocites", "velocities"), ("builtins", "builtin"),
])
def test_spec_unknown_key_suggests_the_closest(key, suggestion):
    spec = {"coordinates": ["x"], "velocities": ["v"], "energy": "v**2/2 + k*x**2", key: 1}
    with pytest.raises(ModelError, match=re.escape(f"sys.toml: [model]: unknown key {key!r}; "
                                                   f"did you mean {suggestion!r}?")):
        model_from_spec(spec, where="sys.toml: [model]")


def test_spec_unrelated_key_lists_the_valid_keys():
    with pytest.raises(ModelError, match=r"unknown key 'zzzzqqq'; valid keys: builtin, .*energy"):
        model_from_spec({"builtin": "duffing", "zzzzqqq": 1})


@pytest.mark.parametrize("extra", [{"energy": "v**2/2 + k*x**2"}, {"name": "mine"},
                                   {"parameters": ["k"]}])
def test_spec_builtin_cannot_be_combined(extra):
    (key,) = extra
    with pytest.raises(ModelError, match=f"'builtin' cannot be combined with {key}"):
        model_from_spec({"builtin": "duffing", **extra})


@pytest.mark.parametrize(("change", "message"), [
    ({"coordinates": "x"}, "'coordinates' must be a list of names"),
    ({"velocities": [1]}, "'velocities' must be a list of names"),
    ({"parameters": "k"}, "'parameters' must be a list of names"),
    ({"parameters": [["k"]]}, "'parameters' must be a list of names"),
    ({"energy": 3}, "'energy' must be a string"),
    ({"energy": ["v**2/2"]}, "'energy' must be a string"),
    ({"name": 4}, "'name' must be a string"),
])
def test_spec_wrong_types_are_rejected(change, message):
    spec = {"coordinates": ["x"], "velocities": ["v"], "energy": "v**2/2 + k*x**2", **change}
    with pytest.raises(ModelError, match=re.escape(f"[model]: {message}")):
        model_from_spec(spec)


@pytest.mark.parametrize(("spec", "message"), [
    ({"builtin": 3}, "'builtin' must be a model name"),
    ({"builtin": ["duffing"]}, "'builtin' must be a model name"),
    ({"builtin": "duffin"}, "unknown model 'duffin'"),
    ({"coordinates": ["x"], "energy": "v**2/2 + k*x**2"}, "missing key 'velocities'"),
    ({"velocities": ["v"], "energy": "v**2/2 + k*x**2"}, "missing key 'coordinates'"),
    ({"coordinates": ["x"], "velocities": ["v"]}, "missing key 'energy'"),
    ({}, "missing key 'coordinates'"),
])
def test_spec_bad_builtin_or_missing_keys(spec, message):
    with pytest.raises(ModelError, match=re.escape(message)):
        model_from_spec(spec)


def test_an_energy_over_several_lines_is_one_expression():
    """A long energy in a TOML multi-line string: its line breaks and indents are spaces."""
    model = model_from_expression("m", "v**2/2\n    + k*x**2/2\n\t+ k3*x**4/4", ["x"], ["v"],
                                  ["k", "k3"])
    assert model.total_energy(np.array([[2.0, 1.0]]), [1.0, 1.0])[0] == pytest.approx(
        0.5 + 2.0 + 4.0)
