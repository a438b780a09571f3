"""The refinement's integrator (hamid.refine.dop853) and its batches in worker processes
(hamid.refine.integration)."""

from __future__ import annotations

import json
import multiprocessing
import pickle
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import PENG, with_noise
from scipy.integrate import solve_ivp

import hamid
from hamid.cli.app import cli
from hamid.data.records import Records
from hamid.errors import UsageError
from hamid.executor import Workers
from hamid.linear import estimate
from hamid.model.dynamics import Dynamics
from hamid.model.models import load_model
from hamid.refine import dop853, integration, trajectory

SAMPLES = Path(__file__).resolve().parents[2] / "sample_data"
OMEGA = np.linspace(0.5, 3.0, 40)   # one pendulum per column, each its own frequency


def _pendulums(t: float, y: np.ndarray) -> np.ndarray:
    q, v = y.reshape(2, -1)
    return np.concatenate([v, -OMEGA**2 * np.sin(q)])


@pytest.mark.parametrize("rtol", [1e-8, 1e-11])
def test_dop853_takes_solve_ivps_steps(rtol):
    """The same arithmetic as scipy's DOP853 with t_eval: the same values to round-off."""
    y0 = np.concatenate([np.linspace(0.1, 2.5, 40), np.zeros(40)])
    times = np.linspace(0.0, 20.0, 401)
    atol = np.full(80, 1e-3 * rtol)
    expected = solve_ivp(_pendulums, (0.0, 20.0), y0, method="DOP853", t_eval=times,
                         rtol=rtol, atol=atol).y.T
    values = dop853.integrate(_pendulums, y0, times, rtol, atol, 10**6)
    np.testing.assert_allclose(values, expected, rtol=1e-13, atol=1e-15)


def test_dop853_meets_its_tolerance_on_harmonic_oscillators():
    """q'' = -w^2 q from (1, 0): q = cos(w t), v = -w sin(w t), between steps too."""
    w = np.array([0.7, 1.0, 2.3])
    times = np.sort(np.random.default_rng(0).uniform(0.0, 30.0, 500))
    times[0] = 0.0
    y0 = np.concatenate([np.ones(3), np.zeros(3)])
    for rtol, limit in ((1e-6, 1e-4), (1e-10, 1e-8)):
        values = dop853.integrate(lambda t, y: np.concatenate([y[3:], -w**2 * y[:3]]), y0,
                                  times, rtol, np.full(6, 1e-3 * rtol), 10**6)
        exact = np.hstack([np.cos(np.outer(times, w)), -w * np.sin(np.outer(times, w))])
        error = np.max(np.abs(values - exact))
        assert error < limit
        assert error > 1e-3 * limit   # the tolerance is what limits it, not chance


def test_dop853_stops_when_the_motion_blows_up_or_the_steps_run_out():
    """y' = y^2 from 1 reaches infinity at t = 1: the step shrinks to nothing there."""
    times = np.linspace(0.0, 2.0, 21)
    with pytest.raises(dop853.IntegrationFailed, match="spacing between numbers"):
        dop853.integrate(lambda t, y: y**2, np.ones(1), times, 1e-8, np.full(1, 1e-12), 10**6)
    with pytest.raises(dop853.TooManySteps, match="10 steps did not reach t = 20"):
        dop853.integrate(_pendulums, np.ones(80), 10 * times, 1e-8, np.full(80, 1e-12), 10)


@pytest.fixture(scope="module")
def noisy_peng():
    """peng-quadratic at 1% noise, 120 s: 10 segments of four periods."""
    system = {**PENG, "simulate": {**PENG["simulate"], "t_end": 120.0}}
    return with_noise(hamid.simulate(system), 0.01, 3)


@pytest.fixture
def spied_pools(monkeypatch):
    """Every pool the refinement starts, by its workers."""
    started = []
    real = integration.started

    def spy(workers, preload):
        started.append(workers.jobs)
        return real(workers, preload)
    monkeypatch.setattr(integration, "started", spy)
    return started


def test_results_do_not_depend_on_the_number_of_workers(noisy_peng, monkeypatch,
                                                        spied_pools):
    """Batches of three segments, every round in two processes against this one: every
    estimate and covariance entry the same, and progress heard of every batch."""
    monkeypatch.setattr(trajectory, "MAX_BATCH", 3)
    monkeypatch.setattr(integration, "PARALLEL_VALUES", 0)
    results, heard = {}, {}
    for jobs in (1, 2):
        messages: list[str] = []
        results[jobs] = hamid.fit(noisy_peng, jobs=jobs, progress=messages.append)
        heard[jobs] = [m for m in messages if m.startswith("trajectory fit")]
    assert spied_pools == [2]          # one pool for the whole refinement, not one a round
    one, two = results[1], results[2]
    assert one.method["refinement"]["applied"] is True
    assert one.method["refinement"]["segments"] > 6
    for name, value in one.estimates.items():
        assert two.estimates[name] == pytest.approx(value, rel=1e-12, abs=0)
    assert two.covariance["names"] == one.covariance["names"]
    np.testing.assert_allclose(two.covariance["matrix"], one.covariance["matrix"], rtol=1e-12,
                               atol=0)
    assert heard[1] == heard[2]
    assert any("3 of " in m for m in heard[2]) and any("6 of " in m for m in heard[2])


def _blas_threads() -> int:
    from threadpoolctl import threadpool_info

    return max(pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas")


def test_a_fit_runs_blas_on_one_thread(noisy_peng, monkeypatch):
    """The linear fit and the refinement's products run BLAS on one thread in this
    process; afterwards BLAS has its threads back."""
    from threadpoolctl import threadpool_limits

    seen = []
    for module, name in ((integration, "blocks"), (estimate, "fit_rows")):
        real = getattr(module, name)

        def spy(*args, _real=real, **kwargs):
            seen.append(_blas_threads())
            return _real(*args, **kwargs)
        monkeypatch.setattr(module, name, spy)
    with threadpool_limits(2, user_api="blas"):
        hamid.fit(noisy_peng, jobs=1)
        assert _blas_threads() == 2
    assert len(seen) > 2 and set(seen) == {1}


def test_a_batch_pickles_once_its_equations_are_compiled():
    """A pendulum's cos energy, compiled by sympy (whose functions do not pickle): the
    batch travels without the compiled functions, and its copy integrates alike."""
    dynamics = Dynamics(load_model(SAMPLES / "pendulum.toml"))
    tau = np.linspace(0.0, 2.0, 41)
    batch = integration.Batch(
        dynamics, [tau, tau], [np.zeros((41, 2)), np.ones((41, 2))], np.ones(2),
        starts=np.array([[[2.0, 0.0], [3.0, 1.0]]]), weights=np.array([[[1.0, 1.0]],
                                                                        [[64.0, 60.0]]]),
        steps=np.zeros(0), tolerance=integration.Tolerance(1e-10, np.full(2, 1e-12), 1e-12,
                                                           50, 1000))
    here = integration.blocks(batch)
    with pytest.raises((pickle.PicklingError, AttributeError, TypeError)):
        pickle.dumps(dynamics)   # compiled now
    there = integration.blocks(pickle.loads(pickle.dumps(batch)))
    np.testing.assert_array_equal(there.cost, here.cost)
    assert here.cost.shape == (2, 2) and np.all(here.cost > 0)


def test_sampled_inputs_travel_without_their_splines_and_make_them_again():
    """The inputs' spline is made once and kept (a refinement's passes reuse it), but
    not pickled to a worker, whose copy makes its own: the same values between the
    samples as scipy's not-a-knot spline of the samples, and the path u(t) writes them
    for each segment's copies."""
    from scipy.interpolate import CubicSpline

    tau = np.linspace(0.0, 1.0, 11)
    values = [np.sin(3 * tau)[:, None], np.cos(2 * tau)[:, None]]
    inputs = integration.SampledInputs([tau, tau], values).part(0, 2)
    assert inputs.spline(1e-9) is inputs.spline(1e-9)
    copy = pickle.loads(pickle.dumps(inputs))
    assert copy._splines == {} and copy._parts == {}
    u = copy.path(3, 1e-9)
    out = np.empty((1, 6))
    u(0.37, out)
    expected = [CubicSpline(tau, v[:, 0])(0.37) for v in values]
    np.testing.assert_allclose(out, [np.repeat(expected, 3)], rtol=1e-13)


def test_symbolic_energies_and_damping_reach_the_workers(monkeypatch, spied_pools):
    """A pendulum's cos energy with viscous damping, in two processes: the results as in
    this one."""
    monkeypatch.setattr(trajectory, "MAX_BATCH", 2)
    monkeypatch.setattr(integration, "PARALLEL_VALUES", 0)
    data, model = (f"{SAMPLES}/pendulum_encoder.csv", f"{SAMPLES}/pendulum.toml")
    one, two = (hamid.fit(data, model, damping="viscous", jobs=jobs) for jobs in (1, 2))
    assert spied_pools == [2]
    assert one.method["refinement"]["applied"] is True
    for name, value in one.estimates.items():
        assert two.estimates[name] == pytest.approx(value, rel=1e-12, abs=0)


def test_a_short_record_stays_in_this_process(noisy_peng, spied_pools):
    """Too little work to pay for starting processes: none started, whatever --jobs."""
    result = hamid.fit(noisy_peng, jobs=2)
    assert result.method["refinement"]["applied"] is True
    assert spied_pools == []


def test_workers_start_at_once_when_a_round_is_expected_to_be_worth_them(spied_pools):
    """From PARALLEL_VALUES expected values, the block starts its processes on entry
    (both running before any round), not at the first round; below, or with one job,
    none."""
    with integration.parallel(Workers(2), integration.PARALLEL_VALUES - 1):
        assert spied_pools == [] and multiprocessing.active_children() == []
    with integration.parallel(Workers(1), integration.PARALLEL_VALUES):
        assert spied_pools == []
    with integration.parallel(Workers(2), integration.PARALLEL_VALUES):
        assert spied_pools == [2]
        assert len(multiprocessing.active_children()) == 2
    assert multiprocessing.active_children() == []


def test_round_values_counts_what_the_first_round_integrates(noisy_peng, monkeypatch):
    """The values the refinement expects of a round, from which its workers start at
    once, against the batches of its first round: every sample in 1 + 2N + p copies,
    less the samples no segment holds."""
    rounds = []
    real = integration.run

    def spy(batches):
        rounds.append(sum(batch.values for batch in batches))
        return real(batches)
    monkeypatch.setattr(integration, "run", spy)
    hamid.fit(noisy_peng, jobs=1)
    records = Records(noisy_peng[["u1", "u2", "v1", "v2"]].to_numpy(), None,
                      noisy_peng["trajectory"].to_numpy(), ())
    expected = trajectory.round_values(records, len(PENG["parameters"]))
    assert expected == (1 + 4 + 6) * 4 * len(noisy_peng)
    assert 0.95 * expected <= rounds[0] <= expected


def test_a_failed_integration_in_a_worker_keeps_the_linear_fit(noisy_peng, monkeypatch):
    """The worker's error comes back as the refinement's reason, and the pool stops."""
    monkeypatch.setattr(trajectory, "MAX_BATCH", 3)
    monkeypatch.setattr(trajectory, "MAX_STEPS_PER_SAMPLE", 0)
    monkeypatch.setattr(trajectory, "MIN_STEP_BUDGET", 0)
    monkeypatch.setattr(integration, "PARALLEL_VALUES", 0)
    refinement = hamid.fit(noisy_peng, jobs=2).method["refinement"]
    assert refinement["applied"] is False
    assert "the integration needs too many steps" in refinement["reason"]


def test_jobs_on_the_command_line(tmp_path, noisy_peng, monkeypatch, spied_pools):
    """`hamid fit --jobs 2` refines in two processes: the report as with --jobs 1."""
    monkeypatch.setattr(trajectory, "MAX_BATCH", 4)
    monkeypatch.setattr(integration, "PARALLEL_VALUES", 0)
    data = tmp_path / "peng.csv"
    noisy_peng.to_csv(data, index=False)
    reports = []
    for jobs in ("1", "2"):
        result = CliRunner().invoke(cli, ["fit", str(data), "--model", "peng-quadratic",
                                          "--jobs", jobs, "--format", "json"])
        assert result.exit_code == 0, result.output
        reports.append(json.loads(result.stdout))
    assert spied_pools == [2]
    assert [p["estimate"] for p in reports[0]["parameters"]] == \
        pytest.approx([p["estimate"] for p in reports[1]["parameters"]], rel=1e-12, abs=0)


@pytest.mark.parametrize("jobs", [0, -1, 1.5, True])
def test_jobs_must_be_a_positive_whole_number(noisy_peng, jobs):
    with pytest.raises(UsageError, match="--jobs must be a whole number of at least 1"):
        hamid.fit(noisy_peng, jobs=jobs)


def test_jobs_zero_on_the_command_line_is_a_usage_error(tmp_path):
    result = CliRunner().invoke(cli, ["fit", str(tmp_path / "x.csv"), "--jobs", "0"])
    assert result.exit_code == 2
    assert "--jobs" in result.stderr and "Traceback" not in result.output


def test_fit_each_keeps_each_refinement_in_its_process(tmp_path, noisy_peng, monkeypatch,
                                                       spied_pools):
    """With --each the files are the parallel work: a fit's refinement starts no pool."""
    monkeypatch.setattr(trajectory, "MAX_BATCH", 3)
    monkeypatch.setattr(integration, "PARALLEL_VALUES", 0)
    data = tmp_path / "peng.csv"
    noisy_peng.to_csv(data, index=False)
    result = CliRunner().invoke(cli, ["fit", "--each", str(data), "--model", "peng-quadratic",
                                      "--jobs", "1", "--format", "jsonl"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["method"]["refinement"]["applied"] is True
    assert spied_pools == []
