"""The trajectory refinement of automatic joint fits (hamid.refine.trajectory)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import (
    DRIVEN_DUFFING_MODEL,
    DUFFING,
    ELASTIC_PENDULUM,
    PENG,
    TWO_MASS,
    spread_band,
    with_noise,
)

import hamid
from hamid import options
from hamid.cli.app import cli
from hamid.data import input_size, writing
from hamid.linear import plan
from hamid.refine import dop853, trajectory
from hamid.refine.integration import common_times

CLEAN = {"peng-quadratic": PENG, "duffing": DUFFING, "two-mass": TWO_MASS,
         "elastic-pendulum": ELASTIC_PENDULUM}


@pytest.mark.parametrize("name", list(CLEAN))
def test_clean_records_are_recovered_exactly(clean_records, name):
    """Polynomial and non-polynomial energies, and a parameter in the kinetic energy."""
    result = hamid.fit(clean_records[name])
    assert result.method["refinement"]["applied"] is True
    assert "refined by fitting the integrated trajectories" in result.method["kind_reason"]
    assert result.estimates == pytest.approx(CLEAN[name]["parameters"], rel=1e-8)


@pytest.fixture
def tolerances(monkeypatch):
    """The tolerance of every integration of the refinement, in order."""
    seen = []
    solve = dop853.integrate

    def counted(fun, y0, times, rtol, *args, **kwargs):
        seen.append(rtol)
        return solve(fun, y0, times, rtol, *args, **kwargs)
    monkeypatch.setattr(dop853, "integrate", counted)
    return seen


def test_clean_data_tighten_at_the_first_step_that_shows_them_clean(clean_records,
                                                                    tolerances):
    """On clean data one integration at the loose tolerance, not a settling at it first;
    the estimates reach the truth to the strict tolerance's accuracy."""
    result = hamid.fit(clean_records["peng-quadratic"])
    assert tolerances[0] == trajectory.LOOSE_RTOL
    assert set(tolerances[1:]) == {trajectory.STRICT_RTOL}
    assert result.estimates == pytest.approx(PENG["parameters"], rel=1e-9)


def test_a_fine_spread_tightens_the_tolerance_only_as_far_as_it_needs(monkeypatch,
                                                                      tolerances):
    """A long record at low noise: its parameters' spread (some 1e-6 relative) asks for a
    tolerance between the loose and the strict one, and the estimates equal those of a
    fit made at the strict tolerance throughout within 1e-3 standard errors."""
    frame = with_noise(hamid.simulate({**PENG, "simulate": {**PENG["simulate"],
                                                            "t_end": 1000.0}}), 0.003, 5)
    adaptive = hamid.fit(frame, jobs=1).to_frame()
    tightened = set(tolerances) - {trajectory.LOOSE_RTOL}
    assert tightened and all(trajectory.STRICT_RTOL < t < trajectory.LOOSE_RTOL
                             for t in tightened)
    monkeypatch.setattr(trajectory, "TOLERANCE_SHARE", 0.0)   # the strict one at once
    tolerances.clear()
    strict = hamid.fit(frame, jobs=1).to_frame()
    assert set(tolerances) == {trajectory.LOOSE_RTOL, trajectory.STRICT_RTOL}
    assert np.all(np.abs(adaptive.estimate - strict.estimate) < 1e-3 * strict.stderr)
    assert np.all(np.abs(adaptive.stderr / strict.stderr - 1) < 1e-4)


def test_segments_sampled_alike_share_their_integration_times():
    """Times of two segments that differ only by rounding are integrated to once; times
    further apart than the resolution stay apart, and every sample finds its time."""
    t = 7.3 + 0.013 * np.arange(500)
    first, second = t[:100] - t[0], t[300:400] - t[300]
    assert not np.array_equal(first, second)            # the rounding this is about
    shifted = first[:50] + 0.005
    resolution = 16 * np.finfo(float).eps * t.max()
    grid, where = common_times([first, second, shifted], resolution)
    assert len(grid) == 150
    joined = np.concatenate([first, second, shifted])
    assert np.max(np.abs(grid[where] - joined)) <= resolution


def test_levels_are_the_energies_of_the_initial_states(clean_records):
    """Duffing E = v^2/2 + k x^2/2 + k3 x^4/4 at each simulated initial state."""
    result = hamid.fit(clean_records["duffing"])
    k, k3 = DUFFING["parameters"].values()
    expected = [s["v"] ** 2 / 2 + k * s["x"] ** 2 / 2 + k3 * s["x"] ** 4 / 4
                for s in DUFFING["initial"]]
    assert [level.h for level in result.energy_levels] == pytest.approx(expected, rel=1e-9)
    assert all(level.stderr is not None and level.stderr < 1e-8
               for level in result.energy_levels)


@pytest.mark.parametrize("name, noise", [("duffing", 0.03), ("two-mass", 0.03),
                                         ("elastic-pendulum", 0.01)])
def test_refinement_beats_the_joint_fit_under_noise(clean_records, name, noise):
    truth = np.array(list(CLEAN[name]["parameters"].values()))
    errors = {"joint": [], "auto": []}
    for seed in range(4):
        frame = with_noise(clean_records[name], noise, seed)
        for method in errors:
            estimate = np.array(list(hamid.fit(frame, method=method).estimates.values()))
            errors[method].append(np.max(np.abs(estimate / truth - 1)))
    assert np.median(errors["auto"]) < np.median(errors["joint"]) / 1.5, errors


def test_a_file_read_in_chunks_is_refined_like_one_in_memory(clean_records, monkeypatch,
                                                             tmp_path):
    """Over the size limit the linear fit reads the file in chunks and the refinement
    holds only the records: the same estimates, errors, levels and residual summary."""
    frame = with_noise(clean_records["duffing"], 0.02, seed=3)
    path = str(tmp_path / "duffing.parquet")
    writing.write_table(frame, path, metadata=frame.attrs["hamid"])
    memory = hamid.fit(path)
    monkeypatch.setattr(options, "STREAM_BYTES", input_size.decoded_bytes(path) - 1)  # made small
    chunked = hamid.fit(path)
    assert chunked.samples is None and memory.samples is not None
    assert chunked.method["refinement"]["applied"] is True
    # the linear fits agree to rounding (the chunked one works from triangular factors)
    rounded = ("block_variance", "refinement")
    assert ({k: v for k, v in chunked.method.items() if k not in rounded}
            == {k: v for k, v in memory.method.items() if k not in rounded})
    assert chunked.method["block_variance"] == pytest.approx(memory.method["block_variance"],
                                                             rel=1e-8)
    refinements = chunked.method["refinement"], memory.method["refinement"]
    for streamed, whole in (refinements, [r["lengthening"] for r in refinements]):
        numbers = [k for k, v in whole.items() if isinstance(v, float)]
        assert [streamed[k] for k in numbers] == pytest.approx([whole[k] for k in numbers],
                                                               rel=1e-8)
        assert ({k: v for k, v in streamed.items() if k not in [*numbers, "lengthening"]}
                == {k: v for k, v in whole.items() if k not in [*numbers, "lengthening"]})
    assert chunked.estimates == pytest.approx(memory.estimates, rel=1e-9)
    assert [p.stderr for p in chunked.parameters] == pytest.approx(
        [p.stderr for p in memory.parameters], rel=1e-6)
    for streamed, whole in zip(chunked.energy_levels, memory.energy_levels, strict=True):
        assert (streamed.h, streamed.stderr) == pytest.approx((whole.h, whole.stderr),
                                                              rel=1e-8)
    assert chunked.residuals["rms"] == pytest.approx(memory.residuals["rms"], rel=1e-8)
    for streamed, whole in zip(chunked.residuals["drift"], memory.residuals["drift"],
                               strict=True):
        assert streamed == pytest.approx(whole, rel=1e-6)
    # records over the memory limit are left unrefined, and the report says why
    monkeypatch.setattr(plan, "REFINEMENT_BYTES", 1000)
    unrefined = hamid.fit(path)
    assert unrefined.method["refinement"]["applied"] is False
    assert "holds the records in memory" in unrefined.method["refinement"]["reason"]
    assert unrefined.estimates == pytest.approx(hamid.fit(path, method="joint").estimates,
                                                rel=1e-10)


def test_progress_hears_every_pass_and_every_batch(clean_records, monkeypatch, tmp_path):
    frame = with_noise(clean_records["duffing"], 0.02, seed=3)
    path = str(tmp_path / "duffing.parquet")
    writing.write_table(frame, path, metadata=frame.attrs["hamid"])
    monkeypatch.setattr(options, "STREAM_BYTES", input_size.decoded_bytes(path) - 1)  # made small
    heard: list[str] = []
    result = hamid.fit(path, progress=heard.append)
    stages = ["periods of the trajectories", "window rows", "records for the trajectory fit",
              "trajectory fit over segments", "residual summary"]
    first = [next(i for i, text in enumerate(heard) if stage in text) for stage in stages]
    assert first == sorted(first)
    assert all(text.startswith(f"{path}: ") for text in heard if "from row" in text)
    refinement = result.method["refinement"]
    length, segments = refinement["segment_seconds"], refinement["segments"]
    ends = [text for text in heard if text.startswith(f"trajectory fit over segments of "
                                                       f"{length:.3g} s") and
            text.endswith(f"{segments:,} of {segments:,} segments")]
    assert ends == [f"trajectory fit over segments of {length:.3g} s: iteration {k}, "
                    f"{segments:,} of {segments:,} segments"
                    for k in range(1, refinement["iterations"] + 1)]
    in_memory: list[str] = []
    hamid.fit(frame, progress=in_memory.append)
    assert in_memory and all(text.startswith("trajectory fit") for text in in_memory)


@pytest.mark.slow
def test_standard_errors_match_the_spread_over_realizations(clean_records):
    """Duffing at 1% noise, 100 realizations: the reported errors are the real spread."""
    n = 100
    fits = [hamid.fit(with_noise(clean_records["duffing"], 0.01, seed)) for seed in range(n)]
    # Were the errors exact, the spread of n estimates over their error would be
    # sqrt(chi2(n - 1) / (n - 1)): 0.77 to 1.24 but for 0.05% on each side, a correct fit
    # failing 0.2% of the time over two parameters (16 realizations allowed only 0.46 to
    # 1.63). The median of the reported errors varies by about 1%.
    low, high = spread_band(n - 1, 0.0005)
    for name in DUFFING["parameters"]:
        estimates = [f.estimates[name] for f in fits]
        stderr = np.median([next(p.stderr for p in f.parameters if p.name == name)
                            for f in fits])
        assert low < np.std(estimates, ddof=1) / stderr < high, name


def test_fixed_parameters_stay_fixed(clean_records):
    result = hamid.fit(clean_records["peng-quadratic"], fix={"a6": 0.2, "w1sq": 1.0})
    assert result.method["refinement"]["applied"] is True
    assert result.estimates == pytest.approx(PENG["parameters"], rel=1e-8)
    fixed = [p for p in result.parameters if p.fixed]
    assert [(p.name, p.estimate, p.stderr) for p in fixed] == [("w1sq", 1.0, None),
                                                                ("a6", 0.2, None)]


def test_damped_records_are_refined_with_their_damping():
    system = {**PENG, "damping": {"c_u1": 0.02, "c_u2": 0.01}}
    clean = hamid.simulate(system)
    result = hamid.fit(clean, damping="viscous")
    assert result.method["refinement"]["applied"] is True
    assert result.estimates == pytest.approx({**PENG["parameters"], **system["damping"]},
                                             rel=1e-7)
    noisy = with_noise(clean, 0.01, seed=2)
    assert hamid.fit(noisy, damping="viscous").method["refinement"]["applied"] is True


def test_derived_velocities_leave_the_trajectory_fit_to_the_positions(clean_records):
    """Savitzky-Golay velocities are not data of their own: the positions alone fit."""
    frame = clean_records["duffing"].drop(columns=["v"])
    joint = hamid.fit(frame, model="duffing", velocity="savgol", method="joint")
    refined = hamid.fit(frame, model="duffing", velocity="savgol")
    assert refined.method["refinement"]["applied"] is True
    truth = np.array(list(DUFFING["parameters"].values()))
    joint_error, refined_error = (
        np.max(np.abs(np.array(list(fit.estimates.values())) / truth - 1))
        for fit in (joint, refined))
    assert refined_error < 1e-7 < joint_error


def test_a_damped_record_fitted_as_conservative_is_judged_on_held_out_segments():
    """The integrated motion cannot follow the decay within the noise: the noise is raised
    to the residual scale, and the held-out check decides; here the refined parameters
    predict as well as the linear ones (the damping is slight over a period), and are
    kept with the sandwich covariance and a warning that says so (the wrong model that is
    refused is in test_refine.py)."""
    damped = hamid.simulate({**DUFFING, "damping": {"c_x": 0.05}})
    auto = hamid.fit(damped)
    refinement = auto.method["refinement"]
    acceptance = refinement["acceptance"]
    assert refinement["noise_chi2_per_dof"] > 1e3
    assert refinement["applied"] == (acceptance["t"] <= acceptance["t_limit"]) is True
    assert refinement["covariance"] == "sandwich"
    assert "sandwich" in auto.method["covariance_description"]
    assert any(w.startswith("the integrated model misses the recording") for w in auto.warnings)


@pytest.mark.parametrize("options, reason", [
    ({"cov": "classical"}, "--cov classical"),
    ({"cov": "bootstrap", "bootstrap": 10, "seed": 1}, "--cov bootstrap"),
    ({"noise": "auto", "bias_correct": True}, "--bias-correct"),
])
def test_options_of_the_linear_fit_skip_the_refinement(clean_records, options, reason):
    frame = with_noise(clean_records["duffing"], 0.01, seed=3)
    result = hamid.fit(frame, **options)
    assert result.method["refinement"]["applied"] is False
    assert reason in result.method["refinement"]["reason"]
    assert reason in result.method["kind_reason"]
    assert result.estimates == hamid.fit(frame, method="joint", **options).estimates


@pytest.mark.parametrize("method", ["energy", "weak", "joint"])
def test_explicit_methods_are_not_refined(clean_records, method):
    assert hamid.fit(clean_records["duffing"], method=method).method["refinement"] is None


def test_cli_reports_the_refinement(clean_records, tmp_path):
    path = tmp_path / "duffing.csv"
    with_noise(clean_records["duffing"], 0.01, seed=4).to_csv(path, index=False)
    runner = CliRunner()
    out = runner.invoke(cli, ["fit", str(path), "--model", "duffing", "--format", "json"])
    assert out.exit_code == 0, out.output
    refinement = json.loads(out.output)["method"]["refinement"]
    assert refinement["applied"] is True
    assert refinement["segments"] >= 1 and refinement["iterations"] >= 1
    assert 0.5 < refinement["chi2_per_dof"] < 1.5
    table = runner.invoke(cli, ["fit", str(path), "--model", "duffing"])
    assert table.exit_code == 0, table.output
    assert "trajectory fit" in table.output


@pytest.mark.slow
@pytest.mark.parametrize("name", ["duffing", "peng-quadratic"])
def test_refined_bounds_cover_the_truth(clean_records, name):
    """1% noise, 100 realizations: the 95% bounds of the refined fit cover 88-99%."""
    from conftest import coverage

    covered = coverage(clean_records[name], CLEAN[name]["parameters"], 0.01, 100)
    for parameter, fraction in covered.items():
        assert 0.88 <= fraction <= 0.99, (parameter, fraction)


def _peng_fit(length: float, noise: float = 0.01, start: float = 1.0,
              within: float = trajectory.SETTLED) -> trajectory.SegmentFit:
    """peng-quadratic, two trajectories of 40 s at `noise`, fitted over segments of
    `length` seconds from the truth times `start`, stopped `within` standard errors."""
    from hamid.data.records import Records

    frame = with_noise(hamid.simulate(PENG), noise, seed=1)
    columns = ["u1", "u2", "v1", "v2"]
    records = Records(frame[columns].to_numpy(), frame["t"].to_numpy(),
                      frame["trajectory"].to_numpy() - 1, (1, 2))
    model = hamid.load_model("peng-quadratic")
    weight = 1 / (noise * frame[columns].std().to_numpy())
    truth = [PENG["parameters"][name] for name in model.parameters]
    return trajectory.fit(model, records, model.dissipative(), np.multiply(truth, start),
                          list(range(len(truth))), length, weight,
                          stop=trajectory.Stop(within))


def test_tied_segments_fit_as_one_segment_per_trajectory():
    """Short segments tied by continuity (multiple shooting) give the fit of one segment
    per trajectory, integrated whole: the same parameters, states, misfit and errors."""
    short = _peng_fit(10.0)
    assert short.segments == 8 and short.groups == 8
    tied = trajectory.join(short, 100, np.inf)
    whole = _peng_fit(1000.0)
    assert tied.segments == 8 and tied.groups == 2 and whole.segments == 2
    free = list(whole.free)
    errors = np.sqrt(np.diag(whole.covariance("scaled")))
    assert np.all(np.abs(tied.theta[free] - whole.theta[free]) < 1e-3 * errors)
    assert tied.dof == whole.dof
    assert tied.chi2_per_dof == pytest.approx(whole.chi2_per_dof, rel=1e-6)
    assert tied.covariance("scaled") == pytest.approx(whole.covariance("scaled"), rel=1e-3)
    assert tied.states[tied.problem.starts] == pytest.approx(whole.states, rel=1e-5, abs=1e-8)
    assert tied.problem.span == pytest.approx(40.0, abs=0.1)
    # the untied short fit sets the state free at every boundary: the stiffnesses' errors
    # are twice as large
    assert np.all(np.sqrt(np.diag(short.covariance("scaled")))[:2] > 1.5 * errors[:2])


def test_tying_fails_where_the_state_steps_grow_too_much(monkeypatch):
    """The continuity carries a state step along the chain of tied segments; past
    MAX_GROWTH the tied fit fails (and the refinement keeps the segments untied)."""
    short = _peng_fit(10.0)
    monkeypatch.setattr(trajectory, "MAX_GROWTH", 1e-3)
    with pytest.raises(trajectory.TooUnstable, match="too unstable to tie"):
        trajectory.join(short, 100, np.inf)


def test_gauss_newton_stops_within_a_thousandth_of_a_standard_error():
    """A fit stops once the point it steps to is within trajectory.SETTLED standard errors
    of the minimum, judged by how fast its steps shrink: fitted on from where it stopped,
    the estimates move by less than that. Started from the short segments' fit, some
    errors off, the tied fit stops at its second step, not at a third that confirms it."""
    short = _peng_fit(10.0)
    tied = trajectory.join(short, 100, np.inf)
    assert tied.iterations == 2
    for fit in (short, tied):
        free = list(fit.free)
        errors = np.sqrt(np.diag(fit.covariance("scaled")))
        on = trajectory.refit(fit, fit.problem.weight)
        assert np.all(np.abs(on.theta[free] - fit.theta[free]) < trajectory.SETTLED * errors)


def test_a_fit_no_step_of_which_lowers_the_misfit_stops_once_damped_to_rounding(
        monkeypatch):
    """Steps turned uphill (as a Jacobian that misjudges the misfit's slope would) fail
    however damped: once the drop they foretell is rounding (the damping grown to 2e13),
    the undamped step judges whether the minimum is reached; failed again, the fit gives
    up there rather than at MAX_ITERATIONS."""
    from hamid.refine import steps

    taken = []
    uphill = steps.Normal.step

    def step(self, damping):
        d_theta, d_x, schur, predicted = uphill(self, damping)
        taken.append(damping)
        return -d_theta, -d_x, schur, predicted

    monkeypatch.setattr(steps.Normal, "step", step)
    with pytest.raises(trajectory.RefinementFailed, match="no step that lowers the misfit"):
        _peng_fit(10.0, start=1.01)
    assert 2 < len(taken) < trajectory.MAX_ITERATIONS / 2
    # undamped, damped more and more, undamped again to judge the minimum, and again
    again = taken.index(0.0, 1)
    assert taken[0] == 0.0 and all(np.diff(taken[:again]) > 0)
    assert taken[again + 1:] == taken[1:again]


def test_a_fit_damped_down_to_its_minimum_is_judged_by_its_undamped_step(monkeypatch):
    """Started damped, the damping never let fall to 0 (LEAST = 0): once a damped step
    foretells a drop of rounding after good steps, the minimum is near, and the fit
    settles on its undamped step where the undamped fit does."""
    from hamid.refine import steps

    undamped = _peng_fit(10.0, start=1.01)
    monkeypatch.setattr(steps, "LEAST", 0.0)
    first = iter([steps.Damping(1e-2)])   # the fit's start damped, then as it is
    monkeypatch.setattr(trajectory, "Damping", lambda: next(first, steps.Damping()))
    damped = _peng_fit(10.0, start=1.01)
    errors = np.sqrt(np.diag(undamped.covariance("scaled")))
    free = list(undamped.free)
    assert np.all(np.abs(damped.theta[free] - undamped.theta[free])
                  < 2 * trajectory.SETTLED * errors)
    assert damped.iterations > undamped.iterations


def test_a_join_starts_from_the_last_point_of_the_fit_it_ties(monkeypatch):
    """Every fit integrates each segment to where its tie to the next would compare it:
    a join's first step needs no integration, and its result equals a join whose first
    point is integrated afresh."""
    short = _peng_fit(10.0)
    problem = short.problem
    t = problem.records.t
    (a0, b0), (a1, _) = problem.pieces[0], problem.pieces[1]
    assert b0 == a1     # the first segment goes on into the second: its end is there
    assert problem.end_times[0] == pytest.approx(t[a1] - t[a0], abs=1e-12)
    last = [s for s in range(len(problem.pieces) - 1)
            if problem.records.group[problem.pieces[s + 1][0]]
            != problem.records.group[problem.pieces[s][0]]]
    assert len(last) == 1   # the last segment of the first trajectory ends at its own sample
    assert problem.end_times[last[0]] == pytest.approx(problem.tau[last[0]][-1], abs=1e-12)

    calls = []
    evaluate = trajectory._normal_equations

    def counted(*args, **kwargs):
        calls.append(1)
        return evaluate(*args, **kwargs)
    monkeypatch.setattr(trajectory, "_normal_equations", counted)
    tied = trajectory.join(short, 100, np.inf)
    assert len(calls) == tied.iterations - 1
    afresh = trajectory._fit_segments(short.problem.tied(100, np.inf), short.point.theta,
                                      short.free, short.point.X0, short.rtol, None)
    assert len(calls) == tied.iterations - 1 + afresh.iterations
    errors = np.sqrt(np.diag(tied.covariance("scaled")))
    free = list(tied.free)
    assert np.all(np.abs(tied.theta[free] - afresh.theta[free]) < 1e-3 * errors)


def test_a_fit_stopped_sooner_is_settled_from_where_it_stopped():
    """A fit stopped within a tenth of a standard error (the refinement's first fit, which
    a joined fit goes on from) is not settled; settled, it goes on from its last point to
    the fit made at once (the same steps), and a settled fit is left as it is."""
    rough = _peng_fit(10.0, start=1.01, within=0.1)
    settled = _peng_fit(10.0, start=1.01)
    assert not rough.settled and settled.settled
    assert rough.iterations < settled.iterations
    on = trajectory.settle(rough)
    errors = np.sqrt(np.diag(settled.covariance("scaled")))
    free = list(settled.free)
    assert on.iterations == settled.iterations
    assert np.all(np.abs(on.theta[free] - settled.theta[free]) < 1e-6 * errors)
    assert trajectory.settle(settled) is settled



@pytest.mark.parametrize("tied", [False, True])
def test_the_inputs_noise_moves_the_parameters_as_a_fit_on_the_noisy_inputs_does(
        tmp_path, tied):
    """`input_response`, the first-order response of the parameters to each recorded input
    sample, applied to a perturbation of the inputs, against the fit run again (to its
    minimum) on the perturbed inputs: over segments fitted each on its own, and over
    segments tied into one."""
    import tomllib

    from hamid.data.records import Records

    truth = {"m": 1.5, "k": 4.0, "k3": 2.0, "c_x": 0.08}
    system = {**tomllib.loads(DRIVEN_DUFFING_MODEL),
              "parameters": {"m": 1.5, "k": 4.0, "k3": 2.0},
              "damping": {"c_x": 0.08}, "initial": [{"x": 0.0, "v": 0.0}],
              "simulate": {"t_end": 30.0, "dt": 0.02}}
    system["forcing"]["signals"] = {"F": {"kind": "multisine", "amplitude": 1.0,
                                          "band": [0.05, 1.0], "seed": 3}}
    frame = with_noise(hamid.simulate(system), 0.01, seed=4)
    path = tmp_path / "driven.toml"
    path.write_text(DRIVEN_DUFFING_MODEL)
    model = hamid.load_model(path)
    damping = model.dissipative(["viscous"])
    X, U = frame[["x", "v"]].to_numpy(), frame[["F"]].to_numpy()
    t, group = frame["t"].to_numpy(), np.zeros(len(frame), int)
    weight = 1 / (0.01 * frame[["x", "v"]].std().to_numpy())

    def fitted(inputs):
        records = Records(X, t, group, (1,), U=inputs)
        fit = trajectory.fit(model, records, damping, list(truth.values()), [0, 1, 2, 3], 7.5,
                             weight)
        return trajectory.settle(trajectory.join(fit, 100, np.inf)) if tied else fit

    fit = fitted(U)
    assert fit.segments == 4 and fit.groups == (1 if tied else 4)
    noise = 0.01 * U.std() * np.random.default_rng(6).standard_normal(U.shape)
    moved = fitted(U + noise).theta - fit.theta
    errors = np.sqrt(np.diag(fit.covariance("scaled")))
    # the response is of the size of the errors; first order, it misses by a few percent
    assert np.all(np.abs(moved) > 0.1 * errors), moved / errors
    shifts = np.einsum("kmi,mi->k", fit.input_response(), noise)
    assert np.all(np.abs(shifts - moved) <= 0.05 * np.abs(moved) + 0.02 * errors), (
        shifts / errors, moved / errors)


def test_coulomb_friction_is_refined_with_its_reversals_rounded():
    """Free decays with viscous and Coulomb friction (reversing some twenty times): the
    refinement runs through the reversals rounded over a thousandth of the velocity's
    scale, reports it, and its intervals hold the truth where the linear fit's errors are
    several times larger."""
    truth = {"k": 1.0, "k3": 0.5, "c_x": 0.05, "mu_x": 0.01}
    system = {**DUFFING, "damping": {"c_x": 0.05, "mu_x": 0.01}}
    frame = with_noise(hamid.simulate(system), 0.01, seed=3)
    refined = hamid.fit(frame, damping="viscous,coulomb")
    refinement = refined.method["refinement"]
    assert refinement["applied"] is True
    [smoothing] = refinement["smoothing"]
    assert smoothing["reversal"] == "v" and smoothing["mean_force_error"] < 2e-3
    assert smoothing["width"] == pytest.approx(1e-3 * np.sqrt(np.mean(frame["v"] ** 2)),
                                               rel=1e-9)
    linear = hamid.fit(frame, damping="viscous,coulomb", method="joint")
    for p in refined.parameters:
        assert p.ci_low <= truth[p.name] <= p.ci_high, p
    errors = [abs(fit.estimates[name] / value - 1) for fit in (refined, linear)
              for name, value in truth.items()]
    assert np.sqrt(np.mean(np.square(errors[:4]))) < np.sqrt(np.mean(np.square(errors[4:]))) / 3
