"""Hardening, round two: inputs that gave internal errors, silent fits or misleading
messages now give the right result or one line naming what is wrong."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers import duffing_system, one_line_error

ROOT = Path(__file__).parents[2]
DUFFING = ROOT / "sample_data" / "duffing.csv"


def _run(hamid_cli, *args, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([*hamid_cli, *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


def _duffing_frame() -> pd.DataFrame:
    return pd.read_csv(DUFFING, comment="#")


def test_times_too_large_to_compute_with(hamid_cli, tmp_path):
    """Times near 1e308 overflowed into NaN: 'cannot convert float NaN to integer'."""
    n = 400
    frame = pd.DataFrame({"t": np.linspace(0, 1e308, n), "x": np.cos(0.1 * np.arange(n)),
                          "v": -np.sin(0.1 * np.arange(n))})
    frame.to_csv(tmp_path / "big.csv", index=False)
    one_line_error(_run(hamid_cli, "fit", "big.csv", "--model", "duffing", cwd=tmp_path), 1,
                    "big.csv: column 't', row 2", "too large to compute with")


def test_a_file_that_does_not_begin_as_parquet_is_refused(hamid_cli, tmp_path):
    """A Parquet file damaged at its start was read from its footer, silently."""
    data = bytearray((ROOT / "sample_data" / "peng_quadratic.parquet").read_bytes())
    data[:4] = b"XXXX"
    (tmp_path / "damaged.parquet").write_bytes(bytes(data))
    for extra in ([], ["--chunk-rows", "500"]):
        one_line_error(_run(hamid_cli, "fit", "damaged.parquet", *extra, cwd=tmp_path), 1,
                        "damaged.parquet: is not a valid Parquet file", "magic bytes")


@pytest.mark.parametrize("chunks", [[], ["--chunk-rows", "500"]])
def test_numbers_stored_as_text_in_parquet_are_read_with_a_note(hamid_cli, tmp_path, chunks):
    frame = _duffing_frame()
    frame.to_parquet(tmp_path / "typed.parquet")
    frame.assign(x=frame["x"].map(repr)).to_parquet(tmp_path / "text.parquet")
    fits = {}
    for name in ("typed.parquet", "text.parquet"):
        done = _run(hamid_cli, "fit", name, "--model", "duffing", "--method", "energy",
                    *chunks, "--format", "json", cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        fits[name] = json.loads(done.stdout)
    note = "text.parquet: column 'x' stores its numbers as text; read them as numbers"
    assert note in fits["text.parquet"]["warnings"]
    assert not any("as text" in w for w in fits["typed.parquet"]["warnings"])
    estimates = {name: [p["estimate"] for p in fit["parameters"]] for name, fit in fits.items()}
    assert estimates["text.parquet"] == pytest.approx(estimates["typed.parquet"], rel=1e-12)


def test_a_noise_larger_than_the_column_names_the_cause(hamid_cli):
    """--noise x=1e308 said the terms 'do not vary along any trajectory'."""
    one_line_error(_run(hamid_cli, "fit", DUFFING, "--noise", "x=1e308", cwd=ROOT), 2,
                    "--noise: x=1e+308", "more than twice the spread")


def test_chunk_rows_beyond_what_pyarrow_takes(hamid_cli):
    """--chunk-rows 1000000000000 gave an int32 OverflowError."""
    done = _run(hamid_cli, "fit", DUFFING, "--chunk-rows", "1000000000000", "--format",
                "json", cwd=ROOT)
    assert done.returncode == 0, done.stderr
    plain = _run(hamid_cli, "fit", DUFFING, "--chunk-rows", "500", "--format", "json",
                 cwd=ROOT)
    found, expected = (json.loads(d.stdout)["parameters"] for d in (done, plain))
    assert [p["estimate"] for p in found] == pytest.approx(
        [p["estimate"] for p in expected], rel=1e-10)


@pytest.mark.parametrize("command", [["fit", DUFFING, "--model"], ["models"]])
def test_a_folder_as_model_says_it_is_a_folder(hamid_cli, tmp_path, command):
    one_line_error(_run(hamid_cli, *command, tmp_path, cwd=ROOT), 1,
                    f"{tmp_path}: is a folder, not a file")


@pytest.mark.parametrize(("field", "text"), [
    ("energy", "v**2/2 + \uff4b*x**2/2 + k*x**4"),           # full-width k beside k
    ("parameters", '["\uff4b"]'),
])
def test_names_that_are_not_ascii_are_refused(hamid_cli, tmp_path, field, text):
    """Python folds the full-width 'ｋ' into 'k': they silently became one parameter."""
    energy = text if field == "energy" else "v**2/2 + \uff4b*x**2/2"
    parameters = text if field == "parameters" else '["\uff4b", "k"]'
    (tmp_path / "m.toml").write_text(
        f'[model]\nname = "m"\ncoordinates = ["x"]\nvelocities = ["v"]\n'
        f'energy = "{energy}"\nparameters = {parameters}\n', encoding="utf-8")
    done = _run(hamid_cli, "fit", DUFFING, "--model", "m.toml", cwd=tmp_path)
    one_line_error(done, 1, "m.toml")
    assert "ASCII" in done.stderr or "cannot be used as a name" in done.stderr


@pytest.mark.parametrize(("name", "count"), [
    ("poly:1:999999999", "999,999,998 terms"), ("poly:1000:3", "167,667,500 terms"),
    ("poly:200000:2", "20,000,100,000 terms"), ("poly:99999999999:2", "about 10^21 terms"),
    ("poly:20:2", "210 terms")])
def test_a_polynomial_too_large_is_refused_before_it_is_built(hamid_cli, name, count):
    """These ran for minutes, or were killed, before."""
    one_line_error(_run(hamid_cli, "models", name, cwd=ROOT), 1, name, count, "at most 200")


def test_ten_thousand_coordinates_without_a_model(hamid_cli, tmp_path):
    """10,000 coordinate/velocity pairs and no model ran past 120 s building poly:N:3."""
    columns = {}
    for i in range(10_000):
        columns[f"x{i}"], columns[f"vx{i}"] = np.zeros(3), np.ones(3)
    pd.DataFrame(columns).to_csv(tmp_path / "wide.csv", index=False)
    one_line_error(_run(hamid_cli, "fit", "wide.csv", cwd=tmp_path), 1,
                    "poly:10000:3 has 166,766,675,000 terms")


def test_a_refinement_through_a_kink_stands_aside(tmp_path):
    """abs(x)**0.5 took 463 s in the refinement (a singular force at x = 0); the linear
    fit is reported with the reason."""
    import hamid
    from hamid.model.models import model_from_expression

    model = model_from_expression("kink", "v**2/2 + k*x**2/2 + k3*abs(x)**0.5", ["x"], ["v"])
    result = hamid.fit(DUFFING, model)
    refinement = result.method["refinement"]
    assert refinement["applied"] is False
    assert "not smooth where abs(x) = 0" in refinement["reason"]


@pytest.mark.parametrize(("energy", "kinks"), [
    ("v**2/2 + k*abs(x)", ["x"]),
    ("v**2/2 + k*x**0.5 + c*sqrt(x**2 + y**2)", ["x", "x**2 + y**2"]),
    ("v**2/2 + k*sin(x)*cos(y)", []),
    ("v**2/2 + k*exp(x)*x**3", []),
])
def test_kinks_of_an_energy(energy, kinks):
    import sympy

    from hamid.model.models import model_from_expression

    model = model_from_expression("m", energy, ["x", "y"], ["v", "w"])
    found = {str(k.expression) for k in model.kinks}
    symbols = {n: sympy.Symbol(n, real=True) for n in ("x", "y")}
    assert found == {str(sympy.sympify(k, locals=symbols)) for k in kinks}


def _system(**changes) -> str:
    """A Duffing system file (`helpers.duffing_system`, 10 s at 0.01 s), some values
    replaced and some tables or keys added (`table__key`)."""
    values = {"t_end": "10", "dt": "0.01"}
    values.update({k: v for k, v in changes.items() if "__" not in k})
    text = duffing_system(**values)
    for key, value in changes.items():
        if "__" in key:
            table, name = key.split("__")
            text = (text.replace("[simulate]\n", f"[simulate]\n{name} = {value}\n")
                    if table == "simulate" else text + f"[{table}]\n{name} = {value}\n")
    return text


HUGE = "1" + "0" * 400


@pytest.mark.parametrize("where", ["k", "x", "t_end", "dt", "noise__x", "damping__c_x"])
def test_integers_beyond_a_double_in_a_system_file(hamid_cli, tmp_path, where):
    """k = 10**400 written out gave an OverflowError."""
    (tmp_path / "sys.toml").write_text(_system(**{where: HUGE}))
    one_line_error(_run(hamid_cli, "simulate", "--config", "sys.toml", "-o", "out.csv",
                         cwd=tmp_path), 1, "sys.toml", "an integer of 401 digits")
    assert not (tmp_path / "out.csv").exists()


@pytest.mark.parametrize(("changes", "words"), [
    ({"simulate__rtol": "1e-300"}, ["rtol = 1e-300", "at least 2.2e-14"]),
    ({"t_end": "1e12", "dt": "1e6"}, ["evaluations of the equations of motion",
                                      "shorten t_end"]),
    ({"damping__c_x": "1e300"}, ["evaluations of the equations of motion"]),
    ({"damping__c_x": "1e6"}, ["the system is stiff", 'method = "radau"']),
    ({"k": "-1.0", "k3": "-0.5", "t_end": "60"}, ["trajectory 1 escapes"]),
], ids=["rtol 1e-300", "span of 1e12 s", "damping 1e300", "stiff damping",
        "unbounded negative stiffness"])
def test_impossible_runs_are_refused_before_they_start(hamid_cli, tmp_path, changes, words):
    (tmp_path / "sys.toml").write_text(_system(**changes))
    one_line_error(_run(hamid_cli, "simulate", "--config", "sys.toml", "-o", "out.csv",
                         cwd=tmp_path), 1, *words)
    assert not (tmp_path / "out.csv").exists()


@pytest.mark.parametrize("changes", [
    {"damping__c_x": "1e6", "simulate__method": '"radau"'},   # the stiff run, as advised
    {"k": "-1.0", "k3": "0.5", "t_end": "60"},                 # a double well: bounded
], ids=["stiff with radau", "double well"])
def test_possible_runs_still_run(hamid_cli, tmp_path, changes):
    (tmp_path / "sys.toml").write_text(_system(**changes))
    done = _run(hamid_cli, "simulate", "--config", "sys.toml", "-o", "out.csv", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert len((tmp_path / "out.csv").read_text().splitlines()) > 1000


def test_a_run_larger_than_memory_is_refused(monkeypatch):
    import hamid
    from hamid import simulation
    from hamid.errors import ModelError

    pages = {"SC_AVPHYS_PAGES": 10, "SC_PAGE_SIZE": 4096}   # 40 kB free
    monkeypatch.setattr(simulation.os, "sysconf", pages.__getitem__)
    system = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
              "initial": [{"x": 1.0, "v": 0.0}], "simulate": {"t_end": 100.0, "dt": 0.01}}
    with pytest.raises(ModelError, match=r"would hold 0\.3 MiB of samples \(10,001 samples "
                                         r"of 2 states\), more than the 0\.0 MiB"):
        hamid.simulate(system)


def test_a_level_just_below_one_is_not_shown_as_100_percent():
    """--level 0.9999999999999999 printed '100% interval'."""
    import hamid

    result = hamid.fit(ROOT / "sample_data" / "henon_heiles.csv", method="energy",
                       level=0.9999999999999999)
    shown = [w for w in result.warnings if "interval contains 0" in w]
    assert shown and all("99.99999999999999% interval" in w for w in shown)


def test_a_simulation_larger_than_the_free_disk_is_refused_before_it_runs(tmp_path,
                                                                       monkeypatch):
    """150 coordinates of 20 million samples (48 GB) started writing."""
    import shutil
    from collections import namedtuple

    from click.testing import CliRunner

    from hamid import simulation
    from hamid.cli import app

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**6, 0, 10_000))
    ran = []
    monkeypatch.setattr(simulation, "run", lambda *a, **k: ran.append(1))
    (tmp_path / "sys.toml").write_text(_system())
    result = CliRunner().invoke(app.cli, ["simulate", "--config", str(tmp_path / "sys.toml"),
                                          "-o", str(tmp_path / "out.csv")])
    assert result.exit_code == 1
    assert "the run would write about" in result.output
    assert "(4,004 values), more than the 0.0 GiB free on its disk" in result.output
    assert ran == [] and not (tmp_path / "out.csv").exists()


def test_many_trajectories_of_two_samples_fit():
    """100,000 labels of 2 samples were killed at 13.4 GB; two-sample trajectories are too
    short to tell their noise, which the noise check must take in its stride."""
    import hamid

    rng = np.random.default_rng(1)
    J = 3_000
    amplitude = rng.uniform(0.5, 1.5, J)
    phase = rng.uniform(0, 2 * np.pi, J)
    t = np.tile([0.0, 0.05], J)
    x = np.repeat(amplitude, 2) * np.cos(t + np.repeat(phase, 2))
    v = -np.repeat(amplitude, 2) * np.sin(t + np.repeat(phase, 2))
    frame = pd.DataFrame({"trajectory": np.repeat(np.arange(J), 2), "t": t, "x": x, "v": v})
    result = hamid.fit(frame, "duffing", method="energy")
    assert result.data["n_trajectories"] == J
    # a harmonic motion: k = 1, k3 = 0, from one energy difference per trajectory
    assert result.estimates["k"] == pytest.approx(1.0, rel=1e-6)
    assert abs(result.estimates["k3"]) < 1e-6


@pytest.mark.parametrize(("keep", "recorded"), [(["x"], "x: position"),
                                                (["a_g"], "x: acceleration"),
                                                (["v", "a_g"], "x: velocity, acceleration")])
def test_chunks_of_a_record_without_positions_and_velocities_are_refused(
        hamid_cli, tmp_path, keep, recorded):
    """Reading in chunks takes each coordinate's position and velocity; other channels
    gave 'no column for coordinate x', which did not say the file is read whole."""
    frame = _duffing_frame()
    frame["a_g"] = -(frame["x"] + 0.5 * frame["x"] ** 3) / 9.80665
    frame[["t", *keep]].to_csv(tmp_path / "part.csv", index=False)
    one_line_error(_run(hamid_cli, "fit", "part.csv", "--model", "duffing", "--chunk-rows",
                        "200", cwd=tmp_path), 2,
                   "part.csv", "--chunk-rows reads each coordinate's position and velocity",
                   f"records {recorded}", "leave out --chunk-rows")


def test_chunks_leave_out_recorded_accelerations_and_say_so(hamid_cli, tmp_path):
    frame = _duffing_frame()
    frame["a_g"] = -(frame["x"] + 0.5 * frame["x"] ** 3) / 9.80665
    frame.to_csv(tmp_path / "all.csv", index=False)
    frame.drop(columns="a_g").to_csv(tmp_path / "xv.csv", index=False)
    reports = [json.loads(_run(hamid_cli, "fit", name, "--model", "duffing", "--chunk-rows",
                               "200", "--format", "json", cwd=tmp_path).stdout)
               for name in ("all.csv", "xv.csv")]
    assert [p["estimate"] for p in reports[0]["parameters"]] == \
        [p["estimate"] for p in reports[1]["parameters"]]
    assert ("all.csv: the accelerations recorded are not read in chunks (leave out "
            "--chunk-rows to fit them too)") in reports[0]["warnings"]
