"""hamid.model.dynamics: Lagrange's equations of a model's energy, against equations of motion
written by hand.

Every expected acceleration below is a closed form derived on paper from the energy (or,
for the double pendulum, the hand-derived 2x2 system solved here with numpy), never a
value the code under test computed. Each case runs with weights shared by every state (the
simulator's way: one Lagrangian, a constant mass matrix folded into the forces) and with
weights per state (the refinement's way: the parts weighed state by state).
"""

from __future__ import annotations

import numpy as np
import pytest

from hamid.errors import ModelError
from hamid.model.dynamics import Dynamics
from hamid.model.models import builtin_model, model_from_expression

MODES = ("shared", "per-state")


def accelerations(model, damping, W, Y, mode):
    """a (N, n) at states Y (2N, n), column j with the weights W[:, j]."""
    dynamics = Dynamics(model, model.dissipative().with_shorthand(damping))
    if mode == "per-state":
        return dynamics.at(W).accelerations(Y)
    return np.column_stack([dynamics.at(W[:, j]).accelerations(Y[:, j:j + 1])
                            for j in range(Y.shape[1])])


def weights(rng, n_states, n_weights, low=0.5, high=2.0):
    """(1, random positive values) for every state."""
    return np.vstack([np.ones(n_states), rng.uniform(low, high, (n_weights - 1, n_states))])


@pytest.mark.parametrize("mode", MODES)
def test_pendulum(mode):
    """w**2/2 - K cos(th): th'' = -K sin(th), far from the small-angle regime."""
    model = model_from_expression("pendulum", "w**2/2 - K*cos(th)", ["th"], ["w"], ["K"])
    rng = np.random.default_rng(0)
    Y = np.vstack([rng.uniform(-3, 3, 5), rng.normal(size=5)])
    W = weights(rng, 5, 2, 1.0, 20.0)
    expected = -W[1] * np.sin(Y[0])
    np.testing.assert_allclose(accelerations(model, (), W, Y, mode)[0], expected,
                               rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("mode", MODES)
def test_duffing_with_every_kind_of_damping(mode):
    """x'' = -k x - k3 x^3 - c v - mu sign(v) - d |v| v."""
    rng = np.random.default_rng(1)
    Y = rng.normal(size=(2, 6))
    W = weights(rng, 6, 6)                        # 1, k, k3, c_x, mu_x, d_x
    x, v = Y
    k, k3, c, mu, d = W[1:]
    expected = -k * x - k3 * x**3 - c * v - mu * np.sign(v) - d * np.abs(v) * v
    found = accelerations(builtin_model("duffing"), ("c_x", "mu_x", "d_x"), W, Y, mode)
    np.testing.assert_allclose(found[0], expected, rtol=1e-13)


@pytest.mark.parametrize("mode", MODES)
def test_viscous_damping_alone(mode):
    """A unit oscillator at rest at x = 0 feels only the damping: a = -c v."""
    model = model_from_expression("spring", "v**2/2 + k*x**2/2", ["x"], ["v"], ["k"])
    Y = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 0.5]])
    W = np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 3.0], [0.2, 0.4, 1.5]])   # 1, k, c_x
    expected = -W[2] * Y[1]
    np.testing.assert_allclose(accelerations(model, ("c_x",), W, Y, mode)[0], expected,
                               rtol=1e-15)


@pytest.mark.parametrize("mode", MODES)
def test_mass_as_a_parameter(mode):
    """(1 + m) v^2/2 + k x^2/2 (an energy needs a parameter-free part):
    x'' = -(k x + c v) / (1 + m)."""
    model = model_from_expression("spring", "v**2/2 + m*v**2/2 + k*x**2/2", ["x"], ["v"],
                                  ["m", "k"])
    rng = np.random.default_rng(7)
    Y = rng.normal(size=(2, 5))
    W = weights(rng, 5, 4)                        # 1, m, k, c_x
    m, k, c = W[1:]
    expected = -(k * Y[0] + c * Y[1]) / (1 + m)
    np.testing.assert_allclose(accelerations(model, ("c_x",), W, Y, mode)[0], expected,
                               rtol=1e-13)


@pytest.mark.parametrize("mode", MODES)
def test_mass_that_changes_with_the_coordinate(mode):
    """(1 + x^2) v^2/2 + k x^2/2: d/dt((1 + x^2) v) = x v^2 - k x, so
    x'' = -(x v^2 + k x) / (1 + x^2)."""
    model = model_from_expression("bead", "(1 + x**2)*v**2/2 + k*x**2/2", ["x"], ["v"], ["k"])
    rng = np.random.default_rng(8)
    Y = rng.normal(size=(2, 5))
    W = weights(rng, 5, 2)
    x, v = Y
    expected = -(x * v**2 + W[1] * x) / (1 + x**2)
    np.testing.assert_allclose(accelerations(model, (), W, Y, mode)[0], expected, rtol=1e-13)


@pytest.mark.parametrize("mode", MODES)
def test_constant_mass_with_coupled_velocities(mode):
    """(v1^2 + m v2^2)/2 + e v1 v2 + k1 x1^2/2 + k2 x2^2/2: M = [[1, e], [e, m]] constant
    but not diagonal, so M a = f gives a1 = (m f1 - e f2)/(m - e^2), a2 = (f2 - e f1)/(m - e^2)
    with f = (-k1 x1, -k2 x2)."""
    model = model_from_expression(
        "coupled", "(v1**2 + m*v2**2)/2 + e*v1*v2 + k1*x1**2/2 + k2*x2**2/2",
        ["x1", "x2"], ["v1", "v2"], ["m", "e", "k1", "k2"])
    rng = np.random.default_rng(9)
    Y = rng.normal(size=(4, 6))
    W = weights(rng, 6, 5)
    W[2] = rng.uniform(-0.6, 0.6, 6)              # |e| < 1 < m: positive definite
    m, e, k1, k2 = W[1:]
    f1, f2 = -k1 * Y[0], -k2 * Y[1]
    det = m - e**2
    expected = np.vstack([(m * f1 - e * f2) / det, (f2 - e * f1) / det])
    np.testing.assert_allclose(accelerations(model, (), W, Y, mode), expected, rtol=1e-12)


TWO_MASS = ("(v1**2 + m*v2**2)/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2 + k3*(x2 - x1)**4/4",
            ["x1", "x2"], ["v1", "v2"], ["m", "k1", "k2", "k3"])


@pytest.mark.parametrize("mode", MODES)
def test_two_masses_the_second_a_parameter(mode):
    """M = diag(1, m): x1'' = -k1 x1 + s, m x2'' = -s, s = k2 (x2 - x1) + k3 (x2 - x1)^3,
    with viscous damping on the second mass (divided by m too)."""
    model = model_from_expression("two-mass", *TWO_MASS)
    rng = np.random.default_rng(2)
    Y = rng.normal(size=(4, 5))
    W = weights(rng, 5, 6)                        # 1, m, k1, k2, k3, c_x2
    x1, x2, _, v2 = Y
    m, k1, k2, k3, c = W[1:]
    stretch = x2 - x1
    spring = k2 * stretch + k3 * stretch**3
    expected = np.vstack([-k1 * x1 + spring, (-spring - c * v2) / m])
    found = accelerations(model, ("c_x2",), W, Y, mode)
    np.testing.assert_allclose(found, expected, rtol=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_elastic_pendulum(mode):
    """A non-polynomial energy: x'' = -k x + kL x / r, y'' = -k y + kL y / r - g."""
    model = model_from_expression(
        "elastic-pendulum", "(vx**2 + vy**2)/2 + k*(x**2 + y**2)/2 - kL*sqrt(x**2 + y**2) + g*y",
        ["x", "y"], ["vx", "vy"], ["k", "kL", "g"])
    rng = np.random.default_rng(3)
    Y = np.vstack([rng.uniform(0.3, 1.5, (2, 4)) * rng.choice([-1, 1], (2, 4)),
                   rng.normal(size=(2, 4))])
    W = weights(rng, 4, 4, 1.0, 12.0)
    x, y = Y[:2]
    k, kL, g = W[1:]
    r = np.hypot(x, y)
    expected = np.vstack([-k * x + kL * x / r, -k * y + kL * y / r - g])
    np.testing.assert_allclose(accelerations(model, (), W, Y, mode), expected, rtol=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_polar_coordinates(mode):
    """(vr^2 + (1 + m) r^2 w^2)/2 + k r^2/2, the mass diag(1, (1 + m) r^2) changing with r
    and m: r'' = (1 + m) r w^2 - k r - c vr, th'' = -2 vr w / r (from d(dL/dw)/dr)."""
    model = model_from_expression("polar", "(vr**2 + r**2*w**2)/2 + m*r**2*w**2/2 + k*r**2/2",
                                  ["r", "th"], ["vr", "w"], ["m", "k"])
    rng = np.random.default_rng(4)
    Y = np.vstack([rng.uniform(0.5, 2, 6), rng.normal(size=(3, 6))])
    W = weights(rng, 6, 4)                        # 1, m, k, c_r
    r, _, vr, w = Y
    m, k, c = W[1:]
    expected = np.vstack([(1 + m) * r * w**2 - k * r - c * vr, -2 * vr * w / r])
    found = accelerations(model, ("c_r",), W, Y, mode)
    np.testing.assert_allclose(found, expected, rtol=1e-12)
    M = Dynamics(model).at(W[:3]).mass_matrix(Y)
    np.testing.assert_allclose(M[:, 0, 0], 1.0)
    np.testing.assert_allclose(M[:, 1, 1], (1 + m) * r**2, rtol=1e-14)
    np.testing.assert_array_equal(M[:, 0, 1], 0.0)
    np.testing.assert_array_equal(M[:, 1, 0], 0.0)


@pytest.mark.parametrize("mode", MODES)
def test_cylindrical_coordinates_with_a_parameter_in_the_mass(mode):
    """Three coordinates (the general solve): (vr^2 + r^2 w^2 + m vz^2)/2 + k r^2/2
    + kz z^2/2: r'' = r w^2 - k r, th'' = -2 vr w / r, z'' = -kz z / m."""
    model = model_from_expression(
        "cylindrical", "(vr**2 + r**2*w**2 + m*vz**2)/2 + k*r**2/2 + kz*z**2/2",
        ["r", "th", "z"], ["vr", "w", "vz"], ["m", "k", "kz"])
    rng = np.random.default_rng(5)
    Y = np.vstack([rng.uniform(0.5, 2, 4), rng.normal(size=(5, 4))])
    W = weights(rng, 4, 4)
    r, _, z, vr, w, _ = Y
    m, k, kz = W[1:]
    expected = np.vstack([r * w**2 - k * r, -2 * vr * w / r, -kz * z / m])
    np.testing.assert_allclose(accelerations(model, (), W, Y, mode), expected, rtol=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_double_pendulum_full_mass_matrix(mode):
    """Unit masses and lengths: M = [[2, cos(p - q)], [cos(p - q), 1]] and, derived by hand,
    M a = (-wq^2 sin(p - q) - 2 g sin p, wp^2 sin(p - q) - g sin q)."""
    model = model_from_expression(
        "double-pendulum", "wp**2 + wq**2/2 + wp*wq*cos(p - q) - g*(2*cos(p) + cos(q))",
        ["p", "q"], ["wp", "wq"], ["g"])
    rng = np.random.default_rng(6)
    Y = np.vstack([rng.uniform(-3, 3, (2, 4)), rng.normal(size=(2, 4))])
    W = weights(rng, 4, 2, 1.0, 10.0)
    p, q, wp, wq = Y
    g = W[1]
    s, c = np.sin(p - q), np.cos(p - q)
    expected = np.empty((2, 4))
    for j in range(4):
        M = np.array([[2.0, c[j]], [c[j], 1.0]])
        f = [-wq[j]**2 * s[j] - 2 * g[j] * np.sin(p[j]), wp[j]**2 * s[j] - g[j] * np.sin(q[j])]
        expected[:, j] = np.linalg.solve(M, f)
    np.testing.assert_allclose(accelerations(model, (), W, Y, mode), expected,
                               rtol=1e-11, atol=1e-12)


def test_right_hand_side_carries_velocities_accelerations_and_drained_power():
    """solve_ivp's layout, variable by variable: (x, v, drained)' = (v, a, -F v), with
    -F v = c v^2 + d |v|^3 for viscous and quadratic damping."""
    model = builtin_model("duffing")
    k, k3, c, d = 1.5, 0.5, 0.3, 0.2
    motion = Dynamics(model, model.dissipative().with_shorthand(("c_x", "d_x"))).at(
        [1.0, k, k3, c, d], drained=True)
    assert motion.rows == 3
    x, v = np.array([0.5, -1.0, 2.0]), np.array([1.0, -0.5, 0.0])
    Y = np.vstack([x, v, [7.0, 8.0, 9.0]])   # the drained energy itself does not matter
    out = motion(0.0, Y.ravel()).reshape(3, 3)
    np.testing.assert_array_equal(out[0], v)
    np.testing.assert_allclose(out[1], -k * x - k3 * x**3 - c * v - d * np.abs(v) * v,
                               rtol=1e-14)
    np.testing.assert_allclose(out[2], c * v**2 + d * np.abs(v)**3, rtol=1e-14)


def test_right_hand_side_without_drained_row():
    """Without `drained` the state is (q, v) only; a 2-DOF state has 4 rows."""
    model = builtin_model("henon-heiles")
    motion = Dynamics(model).at([1.0, 1.0, 1.0, 1.0, -1 / 3])
    assert motion.rows == 4
    x, y, vx, vy = 0.2, -0.3, 0.1, 0.4
    out = motion(0.0, np.array([x, y, vx, vy]))
    # V = (x^2 + y^2)/2 + x^2 y - y^3/3: x'' = -x - 2 x y, y'' = -y - x^2 + y^2
    np.testing.assert_allclose(out, [vx, vy, -x - 2 * x * y, -y - x**2 + y**2], rtol=1e-14)


def test_constant_mass_is_recognised():
    """The simulator checks every sample's mass matrix only when it changes with q."""
    two_mass = model_from_expression("two-mass", *TWO_MASS)
    assert Dynamics(two_mass).at([1.0, 2.0, 1.0, 1.0, 1.0]).constant_mass
    polar = model_from_expression("polar", "(vr**2 + r**2*w**2)/2 + k*r**2/2",
                                  ["r", "th"], ["vr", "w"], ["k"])
    assert not Dynamics(polar).at([1.0, 1.0]).constant_mass


def test_a_singular_mass_is_left_to_the_callers_check():
    """A mass matrix that is not positive definite is no kinetic energy; the simulator
    names the problem from `mass_matrix`, so fixing the weights must not fail first."""
    model = model_from_expression("spring", "v**2/2 + m*v**2/2 + k*x**2/2", ["x"], ["v"],
                                  ["m", "k"])
    motion = Dynamics(model).at([1.0, -1.0, 1.0])
    np.testing.assert_array_equal(motion.mass_matrix(np.zeros((2, 3))), 0.0)


def test_weights_and_damping_names_are_checked():
    model = builtin_model("duffing")
    with pytest.raises(ModelError, match="c_y"):
        model.dissipative().with_shorthand(("c_y",))
    with pytest.raises(ValueError, match="expected"):
        Dynamics(model, model.dissipative().with_shorthand(("c_x",))).at([1.0, 1.0, 1.0])
