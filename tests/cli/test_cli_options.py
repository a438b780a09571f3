"""One command-line test per public option that had none (issue 39): each checks what the
option does to the report or the files written, not only the exit status.

Every case runs `hamid` in a subprocess on small simulated records. The expected values
come from outside the code under test: the simulated parameters, energies written here by
hand from the initial states, counts constructed here (trajectories, weak-form windows
that start every quarter window, panel files), the definitions of AIC and BIC, and a
motion integrated here with scipy for `hamid.simulate_realizations`.
"""

from __future__ import annotations

import copy
import io
import json
import math
import subprocess
from pathlib import Path
from typing import Any

import click
import jsonschema
import numpy as np
import pandas as pd
import pytest
from conftest import DUFFING
from helpers import hamid_command
from referencing import Registry, Resource
from scipy.integrate import solve_ivp

import hamid
from hamid.cli.app import cli

SCHEMAS = Path(__file__).resolve().parents[2] / "hamid" / "schema"
TIMEOUT = 600   # bounds a hang only
K, K3 = DUFFING["parameters"]["k"], DUFFING["parameters"]["k3"]
T_END, DT = DUFFING["simulate"]["t_end"], DUFFING["simulate"]["dt"]
SAMPLES = round(T_END / DT) + 1   # per trajectory


def run(*args: Any, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """`hamid ARGS` in a subprocess."""
    return subprocess.run([*hamid_command(), *map(str, args)], capture_output=True, text=True,
                          timeout=TIMEOUT, cwd=cwd)


def run_json(*args: Any) -> dict[str, Any]:
    """The JSON report of `hamid ARGS --format json`, which must succeed."""
    done = run(*args, "--format", "json")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def duffing_energy(x: float, v: float, k: float = K, k3: float = K3) -> float:
    return v**2 / 2 + k * x**2 / 2 + k3 * x**4 / 4


def _write(frame: pd.DataFrame, path: Path) -> Path:
    frame.to_csv(path, index=False)
    return path


@pytest.fixture(scope="module")
def duffing_csv(tmp_path_factory) -> Path:
    """The clean Duffing record of conftest (2 trajectories), without a metadata line."""
    return _write(hamid.simulate(DUFFING), tmp_path_factory.mktemp("duffing") / "duffing.csv")


# --- fit --order ------------------------------------------------------------------------

def test_order_sets_the_savitzky_golay_order_and_a_higher_one_differentiates_better(
        duffing_csv):
    # On a smooth clean record and a fixed window, a filter of higher order follows the
    # motion more closely: the velocities, and so the energy rows' estimates, are nearer
    # the truth. --method energy shows it undisturbed by the weak-form rows.
    errors = {}
    for order in (3, 7):
        report = run_json("fit", duffing_csv, "--model", "duffing", "--method", "energy",
                          "--velocity", "savgol", "--window", 21, "--order", order)
        assert report["data"]["velocity_source"] == "savgol"
        assert report["data"]["velocity_order"] == order
        assert report["data"]["velocity_window"] == 21
        truth = {"k": K, "k3": K3}
        errors[order] = max(abs(p["estimate"] / truth[p["name"]] - 1)
                            for p in report["parameters"])
    assert errors[3] > 1e-3
    assert errors[7] < 1e-5


def test_a_high_order_takes_a_default_window_it_can_be_computed_over(tmp_path):
    # about 1,130 samples a period: the default window, a tenth of it (113 samples), is beyond
    # where scipy's coefficients of order 9 hold (they are 100% wrong over 101 samples)
    system = copy.deepcopy(DUFFING)
    system["simulate"].update({"t_end": 12.0, "dt": 0.005})
    path = _write(hamid.simulate(system), tmp_path / "fine.csv")
    report = run_json("fit", path, "--model", "duffing", "--method", "energy",
                      "--velocity", "savgol", "--order", 9)
    assert report["data"]["velocity_order"] == 9
    assert report["data"]["velocity_window"] < 101
    estimates = {p["name"]: p["estimate"] for p in report["parameters"]}
    assert estimates == pytest.approx({"k": K, "k3": K3}, rel=1e-6)


@pytest.mark.parametrize(("args", "message"), [
    (["--order", "3"], "Error: --window and --order apply only to --velocity savgol"),
    (["--velocity", "savgol", "--order", "21", "--window", "21"],
     "Error: --window must be odd and larger than --order (21), found 21"),
    (["--velocity", "savgol", "--order", "9", "--window", "101"],
     "Error: --velocity savgol: a filter of order 9 over 101 samples cannot be computed "
     "accurately (scipy's coefficients lose their precision); give a shorter --window or a "
     "lower --order"),
    (["--velocity", "savgol", "--order", "25"],   # refused first by its edge fit
     "Error: --order 25: a polynomial of that degree over the Savitzky-Golay window of 27 "
     "samples is too poorly conditioned to fit; use a lower --order (below 18)"),
])
def test_order_errors_are_one_line(duffing_csv, tmp_path, args, message):
    out = tmp_path / "r.json"
    done = run("fit", duffing_csv, "--model", "duffing", *args, "-o", out)
    assert done.returncode == 2
    assert done.stderr.strip() == message and done.stdout == ""
    assert not out.exists()


# --- fit --trajectory COL ----------------------------------------------------------------

def test_trajectory_column_splits_the_file_into_its_runs(tmp_path):
    system = copy.deepcopy(DUFFING)
    system["initial"].append({"x": -0.7, "v": 0.5})
    labels = {1: "left", 2: "mid", 3: "right"}
    frame = hamid.simulate(system).rename(columns={"trajectory": "run"})
    frame["run"] = frame["run"].map(labels)
    # the runs in another order than simulated: the column, not the row order, tells them
    frame = pd.concat([frame[frame["run"] == name] for name in ("right", "left", "mid")])
    path = _write(frame, tmp_path / "runs.csv")

    report = run_json("fit", path, "--model", "duffing", "--trajectory", "run")
    assert report["data"]["n_trajectories"] == 3
    assert report["data"]["n_samples"] == 3 * SAMPLES
    levels = {level["trajectory"]: level for level in report["energy_levels"]}
    assert set(levels) == set(labels.values())
    for number, name in labels.items():
        start = system["initial"][number - 1]
        assert levels[name]["n_samples"] == SAMPLES
        assert levels[name]["h"] == pytest.approx(duffing_energy(start["x"], start["v"]),
                                                  rel=1e-8)
    estimates = {p["name"]: p["estimate"] for p in report["parameters"]}
    assert estimates == pytest.approx({"k": K, "k3": K3}, rel=1e-8)
    # without the option the file is one trajectory whose time goes back at each new run
    done = run("fit", path, "--model", "duffing")
    assert done.returncode == 1 and done.stdout == ""
    assert "time does not increase" in done.stderr


# --- fit --weak-window -------------------------------------------------------------------

# 1 s is the shortest window the weak form takes at dt = 0.05 s: 20 steps (19.999999999999996
# in floating point, which was refused).
@pytest.mark.parametrize("window", [1.0, 2.0, 4.0])
def test_weak_window_sets_the_windows_of_the_weak_form_rows(duffing_csv, window):
    report = run_json("fit", duffing_csv, "--model", "duffing", "--method", "weak",
                      "--weak-window", window)
    assert report["method"]["kind"] == "weak"
    assert report["method"]["weak_window"] == window
    assert f"windows of {window:g} s (given)" in report["method"]["kind_reason"]
    # windows start every quarter window, as many as fit in each of the two trajectories
    per_trajectory = math.floor((T_END - window) / (window / 4)) + 1
    assert report["residuals"]["blocks"]["weak"]["n_rows"] == 2 * per_trajectory
    estimates = {p["name"]: p["estimate"] for p in report["parameters"]}
    assert estimates == pytest.approx({"k": K, "k3": K3}, rel=1e-4)


def test_a_weak_window_of_too_few_samples_says_how_many_it_holds(duffing_csv):
    done = run("fit", duffing_csv, "--model", "duffing", "--method", "weak",
               "--weak-window", 0.99)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip() == (
        "Error: --method weak is not possible: a weak-form window of 0.99 s holds only "
        "19.8 samples (at least 20 are needed)")


# --- fit --each --scheduler, --ship-data -------------------------------------------------

@pytest.fixture(scope="module")
def cluster():
    """A Dask cluster in this process (its worker a thread), on a port the OS chooses."""
    distributed = pytest.importorskip(
        "distributed", reason="dask[distributed] is not installed (pip install 'hamid[dask]')")
    import dask

    with dask.config.set({"distributed.comm.timeouts.connect": "300s"}), \
            distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                     protocol="tcp", host="127.0.0.1",
                                     dashboard_address=None,
                                     # the scheduler's HTTP server, else on port 8787
                                     scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}
                                     ) as local:
        yield local


@pytest.mark.parametrize(("ship_data", "fitted_k"), [(False, 2.0), (True, K)])
def test_scheduler_fits_on_the_cluster_and_ship_data_sends_the_bytes(
        cluster, tmp_path, monkeypatch, ship_data, fitted_k):
    # The same relative name is a different record here (k = 1) and where the cluster's
    # worker runs (its working directory, k = 2): the estimate tells who read the file.
    here, there = tmp_path / "client", tmp_path / "worker"
    here.mkdir()
    there.mkdir()
    stiffer = copy.deepcopy(DUFFING)
    stiffer["parameters"]["k"] = 2.0
    _write(hamid.simulate(DUFFING), here / "run.csv")
    _write(hamid.simulate(stiffer), there / "run.csv")
    monkeypatch.chdir(there)
    done = run("fit", "--each", "run.csv", "--model", "duffing", "--format", "csv",
               "--scheduler", cluster.scheduler_address,
               *(["--ship-data"] if ship_data else []), cwd=here)
    assert done.returncode == 0, done.stderr
    rows = pd.read_csv(io.StringIO(done.stdout)).set_index("parameter")
    assert list(rows["source"]) == ["run.csv", "run.csv"]
    assert rows.loc["k", "estimate"] == pytest.approx(fitted_k, rel=1e-8)
    assert rows.loc["k3", "estimate"] == pytest.approx(K3, rel=1e-8)


# --- select --columns, --damping, --format, --keep, --criterion --------------------------

def _select_csv(frame: pd.DataFrame, path: Path) -> Path:
    """A record whose velocity column `vx` names its coordinate `x`, as select finds them
    without a model (the library poly:1:4 is then over x)."""
    return _write(frame.rename(columns={"v": "vx"}), path)


@pytest.fixture(scope="module")
def select_csv(tmp_path_factory) -> Path:
    return _select_csv(hamid.simulate(DUFFING), tmp_path_factory.mktemp("select") / "run.csv")


def test_select_columns_maps_model_names_to_file_columns(duffing_csv, tmp_path):
    frame = pd.read_csv(duffing_csv).rename(columns={"x": "pos", "v": "vel"})
    path = _write(frame, tmp_path / "renamed.csv")
    # no column is a coordinate with its velocity by name: poly:1:4 is over q1 (and v1)
    document = run_json("select", path, "--library", "poly:1:4", "--columns",
                        "q1=pos,v1=vel")
    assert document["chosen"] == ["q1**2", "q1**4"]
    assert document["fit"]["data"]["columns"] == {"q1": "pos", "v1": "vel"}
    assert {p["name"]: p["estimate"] for p in document["fit"]["parameters"]} == \
        pytest.approx({"c_2": K / 2, "c_4": K3 / 4}, rel=1e-8)


def test_select_damping_puts_the_damping_coefficients_in_every_model(tmp_path):
    system = copy.deepcopy(DUFFING)
    system["damping"] = {"c_x": 0.05}
    path = _select_csv(hamid.simulate(system), tmp_path / "damped.csv")

    damped = run_json("select", path, "--library", "poly:1:4", "--damping", "viscous")
    assert damped["chosen"] == ["x**2", "x**4"]
    assert damped["fit"]["method"]["damping"] == ["viscous"]
    estimates = {p["name"]: p for p in damped["fit"]["parameters"]}
    assert estimates["c_x"]["role"] == "damping"
    assert {name: p["estimate"] for name, p in estimates.items()} == pytest.approx(
        {"c_2": K / 2, "c_4": K3 / 4, "c_x": 0.05}, rel=1e-6)
    # with the coefficient forced in, the model of damping alone is a candidate too
    assert [] in [c["terms"] for c in damped["candidates"]]

    plain = run_json("select", path, "--library", "poly:1:4")
    assert plain["fit"]["method"]["damping"] == []
    assert [p["name"] for p in plain["fit"]["parameters"]] == ["c_2", "c_4"]
    c_4 = next(p["estimate"] for p in plain["fit"]["parameters"] if p["name"] == "c_4")
    assert abs(c_4 / (K3 / 4) - 1) > 1e-3


def test_select_format_chooses_the_report_whatever_the_file_name(select_csv, tmp_path):
    schema = json.loads((SCHEMAS / "select-1.json").read_text())
    fit_schema = Resource.from_contents(json.loads((SCHEMAS / "fit-1.json").read_text()))
    validator = jsonschema.Draft202012Validator(
        schema, registry=Registry().with_resource("fit-1.json", fit_schema))
    document = run_json("select", select_csv, "--library", "poly:1:4")
    validator.validate(document)
    assert document["schema"] == "hamid.select/1"
    assert set(schema["required"]) <= set(document)

    table = tmp_path / "select.json"
    done = run("select", select_csv, "--library", "poly:1:4", "--format", "table",
               "-o", table)
    assert done.returncode == 0 and done.stdout == "", done.stderr
    assert table.read_text().startswith("hamid select — library poly:1:4 (3 terms)")
    assert "Chosen terms\nx**2, x**4\n" in table.read_text()


def test_select_keep_keeps_the_term_in_every_candidate(select_csv):
    free = run_json("select", select_csv, "--library", "poly:1:4")
    assert any("x**3" not in c["terms"] for c in free["candidates"])
    assert free["kept"] == [] and free["chosen"] == ["x**2", "x**4"]

    kept = run_json("select", select_csv, "--library", "poly:1:4", "--keep", "x**3")
    assert kept["kept"] == ["x**3"]
    assert all("x**3" in c["terms"] for c in kept["candidates"])
    assert kept["chosen"] == ["x**2", "x**3", "x**4"]
    estimates = {p["name"]: p["estimate"] for p in kept["fit"]["parameters"]}
    assert abs(estimates["c_3"]) < 1e-8 * estimates["c_2"]   # the truth has no x**3


def test_select_criterion_is_recorded_and_aic_takes_a_term_bic_leaves_out(tmp_path):
    # A small x**3 term: the fit it adds is worth more than AIC's penalty of 2 a term and
    # less than BIC's log(n_eff), each beyond the margin of 2 by which fewer terms win.
    system = {"model": {"name": "asymmetric", "coordinates": ["x"], "velocities": ["v"],
                        "energy": "v**2/2 + k*x**2/2 + a*x**3/3 + k3*x**4/4"},
              "parameters": {"k": K, "a": 0.0019, "k3": K3},
              "initial": DUFFING["initial"], "simulate": {"t_end": T_END, "dt": DT, "seed": 3},
              "noise": {"relative": 0.01}}
    path = _select_csv(hamid.simulate(system), tmp_path / "asymmetric.csv")
    reports = {criterion: run_json("select", path, "--library", "poly:1:4",
                                   "--criterion", criterion)
               for criterion in ("bic", "aic", "cv")}
    for criterion, report in reports.items():
        assert report["criterion"] == criterion
    assert reports["bic"]["chosen"] == ["x**2", "x**4"]
    assert reports["aic"]["chosen"] == ["x**2", "x**3", "x**4"]
    # the same rows scored: BIC - AIC = (log n_eff - 2) per term
    n_eff = reports["bic"]["rows"]["effective_rows"]
    bic = {tuple(c["terms"]): c["criterion"] for c in reports["bic"]["candidates"]}
    aic = {tuple(c["terms"]): c["criterion"] for c in reports["aic"]["candidates"]}
    assert bic.keys() == aic.keys()
    for terms in bic:
        assert bic[terms] - aic[terms] == pytest.approx(len(terms) * (math.log(n_eff) - 2),
                                                        rel=1e-9)


# --- plot --panels -----------------------------------------------------------------------

PANEL_NUMBERS = {"energy": 1, "residuals": 2, "phase": 3, "motion": 4, "parameters": 5,
                 "correlation": 6}


@pytest.fixture(scope="module")
def saved_fit(duffing_csv, tmp_path_factory) -> Path:
    pytest.importorskip("matplotlib")
    path = tmp_path_factory.mktemp("saved") / "fit.json"
    done = run("fit", duffing_csv, "--model", "duffing", "-o", path)
    assert done.returncode == 0, done.stderr
    return path


@pytest.mark.parametrize(("panels", "files"), [
    ("energy,phase,parameters", ["fig-1-energy.svg", "fig-3-phase.svg",
                                 "fig-5-parameters.svg"]),
    ("Correlation, motion", ["fig-4-motion.svg", "fig-6-correlation.svg"]),
    ("residuals", ["fig.svg"]),   # one panel: the file named
])
def test_plot_panels_by_name_writes_exactly_those_panels(saved_fit, duffing_csv, tmp_path,
                                                         panels, files):
    folder = tmp_path / "figures"
    folder.mkdir()
    done = run("plot", saved_fit, duffing_csv, "-o", folder / "fig.svg", "--panels", panels)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in folder.iterdir()) == files
    names = [name.strip().lower() for name in panels.split(",")]
    for name, file in zip(sorted(names, key=PANEL_NUMBERS.get), files, strict=True):
        # matplotlib writes each text of an SVG as a comment: the title starts "K. "
        assert f"<!-- {PANEL_NUMBERS[name]}. " in (folder / file).read_text()


# --- --help of every command -------------------------------------------------------------

def _options(command: click.Command) -> list[str]:
    return [flag for param in command.params if isinstance(param, click.Option)
            for flag in (*param.opts, *param.secondary_opts)]


@pytest.mark.parametrize("name", sorted(cli.commands))
def test_help_of_every_command_lists_its_options(name):
    done = run(name, "--help")
    assert done.returncode == 0 and done.stderr == ""
    assert done.stdout.startswith(f"Usage: hamid {name} ")
    for flag in [*_options(cli.commands[name]), "--help"]:
        assert flag in done.stdout, flag


def test_help_of_the_group_lists_every_command():
    done = run("--help")
    assert done.returncode == 0 and done.stderr == ""
    commands = done.stdout.split("Commands:")[1].split()
    for name in cli.commands:
        assert name in commands


# --- hamid.simulate_realizations -----------------------------------------------------------

def _clean_duffing(initial: list[dict[str, float]], times: np.ndarray) -> np.ndarray:
    """x and v of each trajectory, integrated here: shape (2, n_trajectories * n_times)."""
    def motion(t: float, y: np.ndarray) -> list[float]:
        return [y[1], -K * y[0] - K3 * y[0]**3]

    runs = [solve_ivp(motion, (0.0, times[-1]), [s["x"], s["v"]], method="DOP853",
                      t_eval=times, rtol=1e-12, atol=1e-12).y for s in initial]
    return np.concatenate(runs, axis=1)


def test_simulate_realizations_gives_noisy_copies_of_one_motion():
    sigma = {"x": 0.01, "v": 0.02}
    system = {**copy.deepcopy(DUFFING), "noise": sigma}
    count, seed = 3, 11
    frames = list(hamid.simulate_realizations(system, count, seed=seed))

    times = np.arange(SAMPLES) * DT
    clean = _clean_duffing(DUFFING["initial"], times)
    n = clean.shape[1]
    assert len(frames) == count
    residuals = []
    for k, frame in enumerate(frames):
        assert list(frame.columns) == ["trajectory", "t", "x", "v"]
        assert frame.shape == (2 * SAMPLES, 4)
        assert list(frame["trajectory"]) == [1] * SAMPLES + [2] * SAMPLES
        np.testing.assert_allclose(frame["t"], np.tile(times, 2), atol=1e-12)
        assert frame.attrs["hamid"]["seed"] == seed + k
        noise = frame[["x", "v"]].to_numpy().T - clean
        for row, (name, level) in enumerate(sigma.items()):
            # the sample std of n normal draws is within 4 of its standard errors
            assert np.std(noise[row]) == pytest.approx(level, rel=4 / math.sqrt(2 * n)), name
            assert abs(np.mean(noise[row])) < 4 * level / math.sqrt(n), name
        residuals.append(noise[0])
    # independent noise in each copy
    assert abs(np.corrcoef(residuals[0], residuals[1])[0, 1]) < 4 / math.sqrt(n)

    again = list(hamid.simulate_realizations(system, count, seed=seed))
    for first, second in zip(frames, again, strict=True):
        pd.testing.assert_frame_equal(first, second)
    shifted = next(hamid.simulate_realizations(system, 1, seed=seed + 1))
    pd.testing.assert_frame_equal(shifted, frames[1])
