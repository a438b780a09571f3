"""The inputs' noise without draws (`hamid.refine.input_noise`): the spline's transpose
against scipy's spline of every unit vector, and each segment's response to its input
samples against the integration run again on perturbed inputs."""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline

import hamid
from hamid.data.records import Records
from hamid.refine import trajectory
from hamid.refine.input_noise import spline_gradient

LINEAR_MODEL = """
[model]
name = "driven-oscillator"
coordinates = ["x"]
velocities = ["v"]
energy = "m*v**2/2 + k*x**2/2"
parameters = ["m", "k"]

[forcing]
inputs = ["F"]
work = "F*x"
"""


@pytest.mark.parametrize("n", [4, 5, 9, 40])
def test_the_spline_gradient_is_scipys_spline_transposed(n):
    """Sum_p z_p s(points_p) by the knots' values: scipy's not-a-knot spline of each
    unit vector, evaluated at the points (some outside the knots), transposed."""
    rng = np.random.default_rng(n)
    x = np.cumsum(rng.uniform(0.5, 1.5, n))
    points = rng.uniform(x[0] - 0.2, x[-1] + 0.2, 60)
    z = rng.standard_normal((60, 3))
    expected = CubicSpline(x, np.eye(n))(points).T @ z
    assert np.max(np.abs(spline_gradient(x, points, z) - expected)) < 1e-12 * np.max(
        np.abs(expected))


@pytest.mark.parametrize(("dt", "accelerations", "jitter"),
                         [(0.02, False, 0.0), (0.1, False, 0.0), (0.02, True, 0.0),
                          (0.02, False, 0.2)])
def test_each_segments_response_is_the_integration_on_perturbed_inputs(
        tmp_path, dt, accelerations, jitter):
    """A linear oscillator driven by a multisine (its motion linear in the force, so a
    finite difference of any size is its derivative): what every segment's scores and end
    state move by when the recorded force is perturbed (integrated again, all copies with
    the perturbed force) is the responses' sum over the perturbed samples, to the
    integrator's tolerance (to 1e-6 of the largest; 1e-5 sampled coarsely: 16 samples per
    period); with an acceleration recorded too, whose residuals move with the force
    itself; and sampled unevenly (each time off by up to a fifth of a step), where the
    segments are not sampled alike and each one's spline is taken to the batch's knots."""
    truth = {"m": 1.5, "k": 4.0, "c_x": 0.08}
    system = {**tomllib.loads(LINEAR_MODEL), "parameters": {"m": 1.5, "k": 4.0},
              "damping": {"c_x": 0.08}, "initial": [{"x": 0.0, "v": 0.0}],
              "simulate": {"t_end": 30.0, "dt": dt}}
    system["forcing"]["signals"] = {"F": {"kind": "multisine", "amplitude": 1.0,
                                          "band": [0.05, 1.0], "seed": 3}}
    frame = hamid.simulate(system)
    path = tmp_path / "driven.toml"
    path.write_text(LINEAR_MODEL)
    model = hamid.load_model(path)
    X, U = frame[["x", "v"]].to_numpy(), frame[["F"]].to_numpy()
    t = frame["t"].to_numpy()
    t = t + jitter * dt * np.random.default_rng(5).uniform(-1, 1, len(t)) * (t > 0)
    records = Records(X, t, np.zeros(len(frame), int), (1,), U=U)
    # at the truth, each segment's samples its own motion (scipy's, through the inputs'
    # spline): no residuals, so the scores move by the motion's move alone, as
    # Gauss-Newton has it (not by the Jacobian's move times the residuals too)
    problem = trajectory._Problem.cut(model, records, model.dissipative(["viscous"]), 7.5,
                                      1 / (0.01 * X.std(axis=0)))
    assert problem.inputs is not None
    motions = []
    for tau, x, inputs in zip(problem.tau, problem.measured, problem.inputs.tau, strict=True):
        force = CubicSpline(inputs, problem.inputs.values[len(motions)])

        def rates(t, y, force=force):
            acceleration = force(t)[..., 0] - truth["c_x"] * y[1] - truth["k"] * y[0]
            return [y[1], acceleration / truth["m"]]

        motion = solve_ivp(rates, (0, tau[-1]), x[0], t_eval=tau, rtol=1e-12, atol=1e-14).y.T
        if accelerations:
            motion = np.column_stack([motion, rates(tau, motion.T)[1]])
        motions.append(motion)
    weight = problem.weight
    if accelerations:
        weight = np.append(weight, 1 / (0.01 * np.std(np.concatenate(motions)[:, 2])))
    problem = dataclasses.replace(problem, measured=motions, weight=weight)
    theta = np.array(list(truth.values()))
    arguments = {"theta": theta, "X0": np.array([x[0, :2] for x in motions]),
                 "free": (0, 1, 2), "rtol": trajectory.STRICT_RTOL,
                 "theta_step": trajectory._theta_step(theta), "batch_done": lambda done: None}
    responses = trajectory._normal_equations(problem=problem, keep=True, **arguments)[3]
    # every score (2 states, 3 parameters) and the end state (2) by themselves
    S, outputs = len(problem.pieces), 2 + 3 + 2
    moves = responses(np.repeat(np.eye(outputs)[None], S, axis=0))
    noise = 0.05 * U.std() * np.random.default_rng(6).standard_normal(U.shape)
    moved = []
    for sign in (1, -1):   # central: the Jacobian's own move times the motion's cancels
        perturbed = dataclasses.replace(problem, inputs=trajectory._segment_inputs(
            dataclasses.replace(records, U=U + sign * noise), problem.pieces))
        at, end, _, _ = trajectory._normal_equations(problem=perturbed, **arguments)
        moved.append(np.concatenate([at.g_x, at.g_t, end], axis=1))
    difference = (moved[0] - moved[1]) / 2
    rows = trajectory._input_rows(records, problem.pieces)
    predicted = np.stack([np.einsum("mri,mi->r", move, noise[a:c])
                          for move, (a, c) in zip(moves, rows, strict=True)])
    assert len(moves) == len(problem.pieces) >= 4
    scale = np.max(np.abs(difference), axis=0)
    assert np.all(np.abs(predicted - difference) <= 1e-4 * scale), (predicted - difference) / scale
