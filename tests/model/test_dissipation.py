"""Rayleigh dissipation functions in model files (`hamid.model.dissipation`).

The truth here is independent of hamid's own equations: two masses on springs with a
dashpot to the ground and one between them, whose equations of motion are written by hand
and integrated by scipy; a double pendulum simulated with known joint friction; forces
computed by hand at chosen states.
"""

from __future__ import annotations

import subprocess

import numpy as np
import pandas as pd
import pytest
from helpers import hamid_command, velocity_findings
from scipy.integrate import solve_ivp

import hamid
from hamid.errors import HamidError, ModelError, UsageError
from hamid.model.dissipation import Dissipation

K1, K2, C1, C2 = 1.0, 2.0, 0.05, 0.03
CHAIN_MODEL = """
[model]
name = "chain"
coordinates = ["x1", "x2"]
velocities = ["v1", "v2"]
energy = "(v1**2 + v2**2)/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2"
parameters = ["k1", "k2"]

[damping]
dissipation = "c1*v1**2/2 + c2*(v2 - v1)**2/2"
parameters = ["c1", "c2"]
"""


def chain_motion(t_end: float = 30.0, dt: float = 0.01) -> pd.DataFrame:
    """x1'' = -k1 x1 + k2 (x2 - x1) - c1 v1 + c2 (v2 - v1), x2'' = -k2 (x2 - x1) - c2 (v2 - v1),
    integrated by scipy from two starts: the truth, written without hamid."""
    def rhs(_t, y):
        x1, x2, v1, v2 = y
        return [v1, v2, -K1 * x1 + K2 * (x2 - x1) - C1 * v1 + C2 * (v2 - v1),
                -K2 * (x2 - x1) - C2 * (v2 - v1)]

    t = np.arange(0.0, t_end + dt / 2, dt)
    frames = []
    for j, start in enumerate(([1.0, -0.5, 0.0, 0.0], [0.2, 0.6, 0.5, -0.3])):
        y = solve_ivp(rhs, (0.0, t_end), start, t_eval=t, rtol=1e-12, atol=1e-13,
                      method="DOP853").y
        frames.append(pd.DataFrame({"trajectory": j + 1, "t": t, "x1": y[0], "x2": y[1],
                                    "v1": y[2], "v2": y[3]}))
    return pd.concat(frames, ignore_index=True)


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    folder = tmp_path_factory.mktemp("chain")
    (folder / "chain.toml").write_text(CHAIN_MODEL)
    chain_motion().to_csv(folder / "chain.csv", index=False)
    return folder


@pytest.mark.parametrize("method", ["energy", "weak", "joint", "auto"])
def test_dashpot_between_masses_is_recovered(chain, method):
    result = hamid.fit(chain / "chain.csv", chain / "chain.toml", method=method)
    expected = {"k1": K1, "k2": K2, "c1": C1, "c2": C2}
    for name, value in expected.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-5, abs=1e-7), name
    roles = {p.name: p.role for p in result.parameters}
    assert roles == {"k1": "energy", "k2": "energy", "c1": "damping", "c2": "damping"}
    assert result.model["dissipation"] == {
        "function": "c1*v1**2/2 + c2*(v2 - v1)**2/2", "parameters": ["c1", "c2"]}


def test_simulate_follows_the_hand_written_equations(tmp_path):
    system = CHAIN_MODEL.replace('parameters = ["c1", "c2"]',
                                 f'parameters = ["c1", "c2"]\nc1 = {C1}\nc2 = {C2}')
    system += (f"\n[parameters]\nk1 = {K1}\nk2 = {K2}\n\n[[initial]]\nx1 = 1.0\nx2 = -0.5\n"
               "v1 = 0.0\nv2 = 0.0\n\n[[initial]]\nx1 = 0.2\nx2 = 0.6\nv1 = 0.5\nv2 = -0.3\n"
               "\n[simulate]\nt_end = 30.0\ndt = 0.01\n")
    (tmp_path / "system.toml").write_text(system)
    frame = hamid.simulate(tmp_path / "system.toml")
    truth = chain_motion()
    for column in ("x1", "x2", "v1", "v2"):
        np.testing.assert_allclose(frame[column], truth[column], rtol=0, atol=1e-8)
    assert frame.attrs["hamid"]["damping"] == {"c1": C1, "c2": C2}
    # fitted without --model: the file's metadata carries the dissipation function
    done = subprocess.run([*hamid_command(), "simulate", "--config", str(tmp_path / "system.toml"),
                           "-o", str(tmp_path / "run.parquet")], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    fitted = hamid.fit(tmp_path / "run.parquet", method="joint")
    assert fitted.estimates["c2"] == pytest.approx(C2, rel=1e-5)
    assert {p.name: p.truth for p in fitted.parameters}["c2"] == C2


def test_shorthand_is_a_term_of_the_same_function(chain):
    """--damping viscous is R = c_q v_q^2/2 per coordinate: the same fit as writing it."""
    written = CHAIN_MODEL.replace('"c1*v1**2/2 + c2*(v2 - v1)**2/2"', '"a*v1**2/2 + b*v2**2/2"')
    written = written.replace('["c1", "c2"]', '["a", "b"]')
    (chain / "per_coordinate.toml").write_text(written)
    plain = chain / "plain.toml"
    plain.write_text(CHAIN_MODEL.split("[damping]")[0])
    by_hand = hamid.fit(chain / "chain.csv", chain / "per_coordinate.toml", method="joint")
    shorthand = hamid.fit(chain / "chain.csv", plain, method="joint", damping="viscous")
    assert shorthand.estimates["c_x1"] == pytest.approx(by_hand.estimates["a"], rel=1e-10)
    assert shorthand.estimates["c_x2"] == pytest.approx(by_hand.estimates["b"], rel=1e-10)
    # both: the function's terms first, then the shorthand
    both = hamid.fit(chain / "chain.csv", chain / "chain.toml", method="joint",
                     damping="coulomb")
    assert [p.name for p in both.parameters] == ["k1", "k2", "c1", "c2", "mu_x1", "mu_x2"]
    assert both.estimates["mu_x1"] == pytest.approx(0.0, abs=1e-6)


def test_forces_and_power_by_hand():
    d = Dissipation.build(("a", "b"), ("wa", "wb"),
                          function="k1*wa**2/2 + k2*(wb - wa)**2/2 + m*abs(wb - wa)",
                          parameters=("k1", "k2", "m"), shorthand=("mu_a",))
    states = np.array([[0.1, 0.2, 1.0, -0.5], [0.3, 0.1, -2.0, 1.0]])
    c = np.array([1.0, 2.0, 0.5, 3.0])
    forces = -(d.force_parts(states) @ c).T   # F_i = -sum_k c_k dR_k/dv_i, (N, n)
    for j, (_, _, wa, wb) in enumerate(states):
        rel = wb - wa
        expected_a = -(c[0] * wa - c[1] * rel - c[2] * np.sign(rel) + c[3] * np.sign(wa))
        expected_b = -(c[1] * rel + c[2] * np.sign(rel))
        assert forces[:, j] == pytest.approx([expected_a, expected_b], rel=1e-14)
        power = d.power_parts(states[j:j + 1]) @ c
        assert power[0] == pytest.approx(-(forces[0, j] * wa + forces[1, j] * wb), rel=1e-14)
    (kink,) = d.kinks[2]   # |wb - wa|: its sign may be written either way
    assert abs(kink(states)) == pytest.approx(np.abs(states[:, 3] - states[:, 2]), rel=1e-15)


@pytest.mark.parametrize(("table", "message"), [
    ('dissipation = "c*v1**2/2 + v2**2"\nparameters = ["c"]', "parameter-free part"),
    ('dissipation = "c*c*v1**2"\nparameters = ["c"]', "not linear"),
    ('dissipation = "c*v1**2/2 + w*v2**2"\nparameters = ["c"]', "unknown symbol 'w'"),
    ('parameters = ["c"]', "'parameters' without a 'dissipation'"),
    ('dissipation = "k2*v1**2/2"\nparameters = ["k2"]', "declared more than once"),
    ('dissipation = 3', "'dissipation' must be a string"),
    ('dissipation = "c*v1**2/2"\nparameters = ["c"]\nd = 1.0', "unknown key 'd'"),
])
def test_bad_dissipation_tables_are_refused(tmp_path, table, message):
    path = tmp_path / "model.toml"
    path.write_text(CHAIN_MODEL.split("[damping]")[0] + "[damping]\n" + table + "\n")
    with pytest.raises(ModelError, match=message):
        hamid.load_model(path)


def test_parameters_default_to_the_other_symbols(tmp_path):
    path = tmp_path / "model.toml"
    path.write_text(CHAIN_MODEL.replace('parameters = ["c1", "c2"]\n', ""))
    assert hamid.load_model(path).dissipation.names == ("c1", "c2")


def test_simulate_needs_a_value_for_each_coefficient(tmp_path):
    system = CHAIN_MODEL + "c1 = 0.1\n[parameters]\nk1 = 1.0\nk2 = 1.0\n[[initial]]\n" \
        "x1 = 1.0\nx2 = 0.0\nv1 = 0.0\nv2 = 0.0\n[simulate]\nt_end = 1.0\ndt = 0.1\n"
    (tmp_path / "system.toml").write_text(system)
    with pytest.raises(ModelError, match="no value for c2"):
        hamid.simulate(tmp_path / "system.toml")


def test_shorthand_name_clash_is_refused(chain, tmp_path):
    path = tmp_path / "clash.toml"
    path.write_text(CHAIN_MODEL.replace('["c1", "c2"]', '["c_x1", "c2"]').replace(
        "c1*v1", "c_x1*v1"))
    with pytest.raises(ModelError, match="c_x1 is both"):
        hamid.fit(chain / "chain.csv", path, method="joint", damping="viscous")


def test_chunks_are_refused_with_a_dissipation_function(chain):
    with pytest.raises(UsageError, match="dissipation function needs the data in memory"):
        hamid.fit(chain / "chain.csv", chain / "chain.toml", chunk_rows=500)


def test_friction_in_the_dissipation_is_refined_through_its_reversals_rounded(chain,
                                                                              tmp_path):
    """A friction term abs(v1) the motion reverses through: the refinement integrates it
    rounded and says so; the data have none, and none is found."""
    path = tmp_path / "coulomb.toml"
    path.write_text(CHAIN_MODEL.replace('"c1*v1**2/2 + c2*(v2 - v1)**2/2"',
                                        '"c1*v1**2/2 + c2*(v2 - v1)**2/2 + m*abs(v1)"')
                    .replace('["c1", "c2"]', '["c1", "c2", "m"]'))
    result = hamid.fit(chain / "chain.csv", path)
    refinement = result.method["refinement"]
    assert refinement["applied"] is True
    [smoothing] = refinement["smoothing"]
    assert smoothing["reversal"] == "v1" and 0 < smoothing["mean_force_error"] < 0.01
    assert result.estimates["m"] == pytest.approx(0.0, abs=1e-6)
    for name, value in {"k1": K1, "k2": K2, "c1": C1, "c2": C2}.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-5), name


def test_the_rounded_friction_law_and_its_error():
    """abs(g) -> sqrt(g**2 + w**2): the force -mu g / sqrt(g**2 + w**2), written out."""
    from hamid.model.dissipation import Dissipation

    exact = Dissipation.build(["x"], ["v"], shorthand=["c_x", "mu_x"])
    assert [str(g.expression) for g in exact.reversals] == ["v"]
    rounded = exact.smoothed([0.01])
    Y = np.array([[0.3, 0.3, 0.3, 0.3], [0.0, 0.005, -0.02, 3.0]])
    c, mu, w = 0.2, 0.5, 0.01
    v = Y[1]
    def force(d, coefficients):   # F_0 = -sum_k c_k dR_k/dv_0 at each state
        return -(d.force_parts(Y.T) @ np.array(coefficients))[:, 0]

    assert force(rounded, [c, mu]) == pytest.approx(
        -c * v - mu * v / np.sqrt(v**2 + w**2), rel=1e-12, abs=1e-15)
    # within the width the force is off by at most mu; far beyond it by mu w^2 / (2 v^2)
    error = force(rounded, [0.0, mu]) - force(exact, [0.0, mu])
    assert np.all(np.abs(error[1:]) <= mu)
    assert abs(error[3]) == pytest.approx(mu * w**2 / (2 * 3.0**2), rel=1e-3)
    cubic = Dissipation.build(["x"], ["v"], function="d*abs(v)**3/3", parameters=["d"])
    assert str(cubic.smoothed([0.1]).parts[0].expression) == "v**2*sqrt(v**2 + 0.01)/3"


def test_cli_reports_the_joint_friction(chain):
    done = subprocess.run([*hamid_command(), "fit", str(chain / "chain.csv"), "--model",
                           str(chain / "chain.toml"), "--method", "joint"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert any(line.split()[:1] == ["c2"] for line in lines), done.stdout


def test_a_missing_model_file_value_is_a_cli_error(chain, tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(CHAIN_MODEL.replace('parameters = ["c1", "c2"]', 'parameters = "c1"'))
    done = subprocess.run([*hamid_command(), "fit", str(chain / "chain.csv"), "--model",
                           str(path)], capture_output=True, text=True, timeout=300)
    assert done.returncode in (1, 2) and done.stdout == ""
    assert "'parameters' must be a list of names" in done.stderr
    assert "Traceback" not in done.stderr


# --- lagging velocities ---------------------------------------------------------------


def lagged(frame: pd.DataFrame, lag: float) -> pd.DataFrame:
    """The velocities as a filter would leave them: v(t - lag), from the exact motion."""
    out = frame.copy()
    for j, piece in frame.groupby("trajectory"):
        t = piece["t"].to_numpy()
        for v in ("v1", "v2"):
            rows = frame["trajectory"] == j
            out.loc[rows, v] = np.interp(t - lag, t, piece[v].to_numpy())
    return out


def check(frame: pd.DataFrame) -> list[str]:
    return [finding.text
            for finding in velocity_findings(frame, ("x1", "x2"), ("v1", "v2"))]


def test_a_lag_of_the_velocities_is_measured_and_said():
    frame = chain_motion(t_end=60.0, dt=0.002)
    assert check(frame) == []
    notes = check(lagged(frame, 0.004))
    assert len(notes) == 2 and all("lag behind" in n for n in notes)
    found = float(notes[0].split(" by ")[1].split(" s ")[0])
    assert found == pytest.approx(0.004, rel=0.05)
    assert "a channel filtered" in notes[0]


def test_noise_alone_is_not_a_lag():
    frame = chain_motion(t_end=60.0, dt=0.002)
    rng = np.random.default_rng(3)
    for c in ("x1", "x2", "v1", "v2"):
        frame[c] += 0.01 * frame[c].std() * rng.standard_normal(len(frame))
    assert check(frame) == []


def test_errors_are_hamid_errors():
    assert issubclass(ModelError, HamidError)


def test_the_fitted_result_simulates_and_draws_its_dissipation(chain):
    pytest.importorskip("matplotlib")
    result = hamid.fit(chain / "chain.csv", chain / "chain.toml", method="joint")
    t = np.arange(0.0, 30.0 + 0.005, 0.01)
    motion = result.simulate([{"x1": 1.0, "x2": -0.5, "v1": 0.0, "v2": 0.0}], t)
    truth = chain_motion().query("trajectory == 1")
    np.testing.assert_allclose(motion["x2"], truth["x2"], rtol=0, atol=1e-5)
    figure = result.plot(panels=[1])
    (axes, *_) = figure.axes
    assert axes.get_ylabel()


# --- coverage of a simulated double pendulum with joint friction ------------------------

DOUBLE_PENDULUM = """
[model]
name = "double-pendulum"
coordinates = ["theta1", "theta2"]
velocities = ["omega1", "omega2"]
energy = '''omega1**2/2 + J2*omega2**2/2 + B*cos(theta1 - theta2)*omega1*omega2
  + C1*cos(theta1) + C2*cos(theta2)'''
parameters = ["J2", "B", "C1", "C2"]

[damping]
dissipation = "k1*omega1**2/2 + k2*(omega2 - omega1)**2/2"
parameters = ["k1", "k2"]
k1 = 0.042
k2 = 0.0018

[parameters]
J2 = 0.5568
B = 0.4913
C1 = 58.96
C2 = 27.90

[[initial]]
theta1 = 3.6
theta2 = 3.0
omega1 = 0.0
omega2 = 1.0

[[initial]]
theta1 = 2.3
theta2 = 2.0
omega1 = 0.0
omega2 = 0.0

[simulate]
t_end = 8.0
dt = 0.01

[noise]
relative = 0.01
"""
DP_TRUTH = {"J2": 0.5568, "B": 0.4913, "C1": 58.96, "C2": 27.90, "k1": 0.042, "k2": 0.0018}


def _covered(seed: int) -> dict[str, bool]:
    """Whether each 95% interval of the default fit of one noisy realization holds the truth."""
    import tomllib

    system = tomllib.loads(DOUBLE_PENDULUM)
    from hamid.model.models import damping_table, model_from_spec

    frame = hamid.simulate(system, seed=seed)
    model, _ = damping_table(model_from_spec(system["model"]), system["damping"])
    result = hamid.fit(frame, model)
    assert result.method["refinement"]["applied"] or result.method["refinement"]["reason"]
    return {p.name: p.ci_low <= DP_TRUTH[p.name] <= p.ci_high for p in result.parameters}


@pytest.mark.slow
def test_joint_friction_intervals_cover_the_truth():
    """Every parameter of the default fit, friction included: 90-98% coverage of the 95%
    intervals over 100 realizations at 1% noise (measured 95-97%)."""
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(2) as pool:
        runs = list(pool.map(_covered, range(100)))
    for name in DP_TRUTH:
        coverage = np.mean([run[name] for run in runs])
        assert 0.90 <= coverage <= 0.98, (name, coverage)


def test_the_table_names_the_dissipation_function(chain):
    done = subprocess.run([*hamid_command(), "fit", str(chain / "chain.csv"), "--model",
                           str(chain / "chain.toml"), "--method", "weak", "--damping",
                           "coulomb"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    (row,) = [line for line in done.stdout.splitlines() if line.startswith("damping ")]
    assert row.split(None, 1)[1] == "R = c1*v1**2/2 + c2*(v2 - v1)**2/2, coulomb"


def test_noisy_short_records_show_no_lag():
    """Noise alone scatters the measured lag; a lag the noise could fake is not said
    (before the significance test, one noisy Duffing record in a few was told of a lag)."""
    from helpers import duffing_system

    text = duffing_system(t_end="20.0", dt="0.05") + "\n[noise]\nrelative = 0.02\n"
    for seed in range(10):
        frame = hamid.simulate(__import__("tomllib").loads(text), seed=seed)
        result = hamid.fit(frame, "duffing", method="joint")
        assert not [w for w in result.warnings if "lag" in w], seed
