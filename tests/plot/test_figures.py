"""The fit's pictures (hamid.plot.figures, `hamid plot`, `fit --plot`): each panel is rendered to
PNG from the bundled Henon-Heiles sample and checked: not blank, as many lines, points
and bars as the data have, the values drawn equal to ones computed here from the file,
axis labels set, a title that names the file and the method."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from conftest import DUFFING
from helpers import hamid_command
from scipy.integrate import cumulative_trapezoid

import hamid
from hamid.cli.app import cli
from hamid.errors import UsageError
from hamid.plot import figures, fitted
from hamid.result.fit_result import FitResult

pytest.importorskip("matplotlib")

from matplotlib.collections import PathCollection, PolyCollection  # noqa: E402
from matplotlib.contour import ContourSet  # noqa: E402
from matplotlib.image import imread  # noqa: E402

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data" / "henon_heiles.csv"


@pytest.fixture(scope="module")
def fit() -> FitResult:
    return hamid.fit(str(SAMPLE))


@pytest.fixture(scope="module")
def table() -> pd.DataFrame:
    return pd.read_csv(SAMPLE, comment="#")


@pytest.fixture(scope="module")
def noise() -> dict[str, float]:
    """The noise the simulator put into the sample (its metadata line)."""
    first = SAMPLE.read_text().splitlines()[0]
    return json.loads(first.removeprefix("# hamid: "))["noise"]


def _page(fit, panel: str):
    (name, figure), = figures.pages(fit.to_dict(), fit.recording, panel)[0]
    assert name == panel
    return figure


def _png(figure) -> np.ndarray:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return imread(io.BytesIO(buffer.getvalue()))


def _data_axes(figure) -> list:
    """The axes of a panel, colour bars left out."""
    return [ax for ax in figure.axes if ax.get_label() != "<colorbar>"]


def _check_picture(figure) -> None:
    """Not blank, titled with the file and the method, every axis labelled."""
    pixels = _png(figure)[..., :3]
    assert pixels.std() > 0.1 and (pixels.mean(axis=2) < 0.9).mean() > 0.02
    title = figure.get_suptitle()
    assert "henon_heiles.csv" in title and "method joint" in title
    assert any(ax.get_xlabel() for ax in _data_axes(figure))
    assert all(ax.get_ylabel() or ax.get_title() or ax.get_title(loc="left")
               for ax in _data_axes(figure))


def _energy(table: pd.DataFrame, estimates: dict[str, float]) -> np.ndarray:
    """The Henon-Heiles energy, written out here."""
    x, y, vx, vy = (table[c].to_numpy() for c in ("x", "y", "vx", "vy"))
    a, b, c, d = (estimates[k] for k in "abcd")
    return (vx**2 + vy**2) / 2 + a * x**2 / 2 + b * y**2 / 2 + c * x**2 * y + d * y**3


def test_energy_panel_draws_each_trajectorys_energy_and_level(fit, table):
    figure = _page(fit, "energy")
    _check_picture(figure)
    axes = _data_axes(figure)
    assert len(axes) == 2
    energy = _energy(table, fit.estimates)
    for ax, (label, rows) in zip(axes, table.groupby("trajectory"), strict=True):
        drawn, level = ax.get_lines()
        np.testing.assert_allclose(drawn.get_ydata(), energy[rows.index], rtol=1e-12)
        np.testing.assert_allclose(drawn.get_xdata(), rows["t"])
        h = next(lv.h for lv in fit.energy_levels if lv.trajectory == label)
        np.testing.assert_allclose(level.get_ydata(), h)
        assert sum(isinstance(c, PolyCollection) for c in ax.collections) == 1  # the band


def test_energy_panel_of_a_damped_fit_draws_h_minus_the_dissipated_work():
    """Viscous damping c v: the level line is h - c * integral of v² dt (trapezoid rule
    here), and the fitted energy follows it."""
    frame = hamid.simulate({**DUFFING, "damping": {"c_x": 0.05}})
    result = hamid.fit(frame, damping="viscous")
    figure = figures.figure(result.to_dict(), result.recording, "energy")
    first = frame[frame.trajectory == 1]
    drawn, level = _data_axes(figure)[0].get_lines()
    c, h = result.estimates["c_x"], result.energy_levels[0].h
    work = c * cumulative_trapezoid(first["v"] ** 2, first["t"], initial=0)
    np.testing.assert_allclose(level.get_ydata(), h - work, atol=2e-4 * h)
    assert level.get_label() == "h − dissipated work"
    energy = first["v"] ** 2 / 2 + first["x"] ** 2 / 2 + first["x"] ** 4 / 8
    np.testing.assert_allclose(drawn.get_ydata(), energy, rtol=1e-6)
    assert np.ptp(drawn.get_ydata()) > 0.1 * h      # it loses energy: the test sees it


def test_noise_band_holds_the_energys_scatter(fit):
    """The band is twice the noise the measurement puts into E: about 95% of the samples'
    energies lie within it (the noise is known here: the simulator added it)."""
    e = fitted.energies(fit.to_dict(), fit.recording)
    inside = np.abs(e.energy - e.level) <= 2 * e.noise
    assert 0.9 < inside.mean() < 0.99


def test_residuals_panel(fit, table):
    figure = _page(fit, "residuals")
    _check_picture(figure)
    series, histogram, correlation = _data_axes(figure)
    energy = _energy(table, fit.estimates)
    h = table["trajectory"].map({lv.trajectory: lv.h for lv in fit.energy_levels})
    traces = [line for line in series.get_lines() if line.get_label().startswith("trajectory")]
    assert len(traces) == 2
    np.testing.assert_allclose(np.concatenate([t.get_ydata() for t in traces]),
                               energy - h.to_numpy(), atol=1e-12)
    (bars,) = histogram.containers
    assert len(bars) == int(np.sqrt(len(table)))        # 40 bins for 1602 samples
    assert sum(b.get_height() * b.get_width() for b in bars) == pytest.approx(1.0)
    (normal,) = histogram.get_lines()
    x, density = normal.get_xydata().T
    np.testing.assert_allclose(density, np.exp(-x**2 / 2) / np.sqrt(2 * np.pi))
    (lags,) = correlation.containers
    assert len(lags) == 40 and lags[0].get_x() + lags[0].get_width() / 2 == pytest.approx(1)
    assert lags[0].get_height() == pytest.approx(fit.residuals["lag1_autocorrelation"],
                                                 rel=1e-9)


def test_phase_panel_draws_every_sample_and_a_contour_per_trajectory(fit, table):
    figure = _page(fit, "phase")
    _check_picture(figure)
    axes = _data_axes(figure)
    # a row per trajectory, a plot per coordinate
    cells = [(k, q, v) for k in (1, 2) for q, v in [("x", "vx"), ("y", "vy")]]
    assert [(ax.get_xlabel(), ax.get_ylabel()) for ax in axes] == [c[1:] for c in cells]
    for ax, (k, q, v) in zip(axes, cells, strict=True):
        (points,) = [c for c in ax.collections if isinstance(c, PathCollection)]
        np.testing.assert_array_equal(points.get_offsets(),
                                      table.loc[table.trajectory == k, [q, v]].to_numpy())
        (contour,) = [c for c in ax.collections if isinstance(c, ContourSet)]
        assert contour.get_zorder() > points.get_zorder()    # the line above the points
        assert ax.get_title(loc="left") == f"trajectory {k}"


def test_phase_contour_of_one_degree_of_freedom_is_the_orbit(clean_records):
    """Duffing without noise: the contour of trajectory 1 is its orbit, the curve of the
    energy it started with, v²/2 + x²/2 + x⁴/8 = 5/8 (at rest at x = 1)."""
    result = hamid.fit(clean_records["duffing"])
    figure = figures.figure(result.to_dict(), result.recording, "phase")
    ax = _data_axes(figure)[0]
    contour = next(c for c in ax.collections if isinstance(c, ContourSet))
    x, v = contour.get_paths()[0].vertices.T
    np.testing.assert_allclose(v**2 / 2 + x**2 / 2 + x**4 / 8, 5 / 8, rtol=2e-3)
    assert x.max() == pytest.approx(1.0, abs=2e-3) and x.min() == pytest.approx(-1.0, abs=2e-3)


def test_contours_are_solid_at_negative_levels(clean_records):
    """A pendulum's levels are negative (E = ω²/2 − K cos θ), which matplotlib would dash;
    its contour is still the orbit: at rest at θ = 1.2, E = −9 cos 1.2."""
    result = hamid.fit(clean_records["pendulum"])
    figure = figures.figure(result.to_dict(), result.recording, "phase")
    contour = next(c for c in _data_axes(figure)[0].collections if isinstance(c, ContourSet))
    assert contour.get_linestyle() == [(0, None)]     # solid
    theta, omega = contour.get_paths()[0].vertices.T
    np.testing.assert_allclose(omega**2 / 2 - 9 * np.cos(theta), -9 * np.cos(1.2), rtol=2e-3)


def test_motion_panel_names_its_one_coordinate():
    """One coordinate: its axis says its name (several share the axis as q)."""
    result = hamid.fit(hamid.simulate({**DUFFING, "simulate": {"t_end": 10.0, "dt": 0.05}}))
    motion = _data_axes(_page(result, "motion"))[0]
    assert motion.get_ylabel().split()[0] == "x"


def test_motion_panel_fits_the_recording_to_its_noise(fit, table, noise):
    figure = _page(fit, "motion")
    _check_picture(figure)
    axes = _data_axes(figure)
    assert len(axes) == 4        # motion and misfit, per trajectory
    # the lengthened segments the estimates come from, not the first ones
    length = fit.method["refinement"]["lengthening"]["segment_seconds"]
    assert length > fit.method["refinement"]["segment_seconds"]
    first = table[(table.trajectory == 1) & (table.t <= length + 1e-9)]
    lines = axes[0].get_lines()
    assert len(lines) == 4       # recorded and fitted, per coordinate
    np.testing.assert_array_equal(lines[0].get_ydata(), first["x"])
    np.testing.assert_array_equal(lines[2].get_ydata(), first["y"])
    misfit = [line.get_ydata() for line in axes[1].get_lines()[:2]]
    assert np.std(misfit[0]) == pytest.approx(noise["x"], rel=0.15)
    assert np.std(misfit[1]) == pytest.approx(noise["y"], rel=0.15)


def test_motion_panel_says_positions_it_did_not_record(damped):
    """From accelerations alone the positions drawn are reconstructed, and said to be."""
    frame = hamid.simulate({**DUFFING, "damping": {"c_x": 0.05}})
    accelerations = frame[["trajectory", "t"]].assign(
        a=-(frame["x"] + 0.5 * frame["x"] ** 3 + 0.05 * frame["v"]))
    fit = hamid.fit(accelerations, "duffing", damping="viscous")
    figure = _page(fit, "motion")
    motion = _data_axes(figure)[0]
    assert [line.get_label() for line in motion.get_lines()][:2] == ["x reconstructed",
                                                                     "x fitted model"]
    assert "positions not recorded are shown as reconstructed" in \
        figure.get_supxlabel().replace("\n", " ")
    assert "reconstructed" not in _page(damped, "motion").get_supxlabel()


def test_parameters_panel_draws_each_interval_and_the_truth(fit):
    figure = _page(fit, "parameters")
    _check_picture(figure)
    axes = _data_axes(figure)
    assert len(axes) == len(fit.parameters)
    for ax, p in zip(axes, fit.parameters, strict=True):
        (bars,) = ax.containers
        point, _, (segments,) = bars
        assert point.get_xdata()[0] == p.estimate
        np.testing.assert_allclose(segments.get_segments()[0][:, 0], [p.ci_low, p.ci_high])
        truth = [line.get_xdata()[0] for line in ax.get_lines() if line.get_linestyle() == "--"]
        assert truth == [p.truth]
        assert ax.get_title(loc="left").startswith(f"{p.name} = ")


def test_correlation_panel_is_the_reports_correlation(fit):
    figure = _page(fit, "correlation")
    _check_picture(figure)
    (ax,) = _data_axes(figure)
    (image,) = ax.get_images()
    matrix = np.array(fit.covariance["matrix"])
    sd = np.sqrt(np.diag(matrix))
    np.testing.assert_allclose(image.get_array(), matrix / np.outer(sd, sd), rtol=1e-12)
    assert len(ax.texts) == 16
    assert [t.get_text() for t in ax.get_xticklabels()] == fit.covariance["names"]


def test_one_figure_of_all_panels(fit):
    figure = fit.plot()
    assert len(figure.subfigs) == 6
    assert [s.get_suptitle().split(".")[0] for s in figure.subfigs] == \
        ["1", "2", "3", "4", "5", "6"]


def test_a_panel_in_a_given_subplot(fit):
    from matplotlib.figure import Figure

    figure = Figure()
    left, right = figure.subplots(1, 2)
    assert fit.plot("parameters", ax=right) is figure
    assert left in figure.axes and right not in figure.axes
    (panel,) = figure.subfigs    # its legend strip and its plots
    assert sum(len(part.axes) for part in panel.subfigs) == len(fit.parameters)
    with pytest.raises(UsageError, match="ax: give one panel"):
        fit.plot(["parameters", "correlation"], ax=left)


def test_a_result_read_back_draws_only_what_needs_no_data(fit):
    loaded = FitResult.from_dict(fit.to_dict())
    figure = loaded.plot()
    assert [s.get_suptitle()[:2] for s in figure.subfigs] == ["5.", "6."]
    with pytest.raises(UsageError, match=r"^panel 1 \(energy\) needs the data the fit read"):
        loaded.plot(1)


@pytest.mark.parametrize(("panels", "names"), [
    ("1,phase", ("energy", "phase")), (5, ("parameters",)),
    (["6", "energy"], ("energy", "correlation")),
])
def test_panels_by_number_or_name(fit, panels, names):
    assert figures.choose(fit.to_dict(), fit.recording, panels)[0] == names


def test_unknown_panel():
    with pytest.raises(UsageError, match=r"unknown panel 'speed' \(choose from 1 energy, "):
        figures.parse_panels("speed")


def test_drawing_opens_no_window_and_imports_no_pyplot(tmp_path):
    code = (f"import sys, hamid\nr = hamid.fit({str(SAMPLE)!r}, method='joint')\n"
            f"r.plot().savefig({str(tmp_path / 'f.png')!r})\n"
            "print('matplotlib.pyplot' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={"PATH": "/usr/bin:/bin", "DISPLAY": "",
                              "PYTHONPATH": os.environ["PYTHONPATH"]})
    assert out.stdout.strip() == "False" and (tmp_path / "f.png").stat().st_size > 10_000


# --- panel 7, the backbone -----------------------------------------------------------------


@pytest.fixture(scope="module")
def damped() -> FitResult:
    """A damped hardening Duffing (unit mass, c = 0.05), two free decays."""
    return hamid.fit(hamid.simulate({**DUFFING, "damping": {"c_x": 0.05},
                                     "noise": {"x": 2e-3, "v": 2e-3}}), damping="viscous")


def _duffing_frequency(k: float, k3: float, amplitude: np.ndarray) -> np.ndarray:
    """The exact frequency of x'' + k x + k3 x^3 = 0 at amplitude A (complete elliptic
    integral of the first kind, parameter m = k3 A^2 / (2 (k + k3 A^2)))."""
    from scipy.special import ellipk

    stiff = k + k3 * amplitude**2
    return np.sqrt(stiff) / (4 * ellipk(k3 * amplitude**2 / (2 * stiff)))


def test_the_backbone_is_drawn_only_when_asked_for(damped):
    assert "backbone" not in figures.choose(damped.to_dict(), damped.recording)[0]
    assert figures.choose(damped.to_dict(), damped.recording, 7)[0] == ("backbone",)
    assert len(damped.plot().subfigs) == 6


def test_backbone_panel_draws_the_fitted_backbone_its_bands_and_the_recorded_periods(damped):
    figure = _page(damped, "backbone")
    frequency, damping = _data_axes(figure)
    model, *recorded = frequency.get_lines()
    amplitude = np.asarray(model.get_xdata())
    k, k3, c = (damped.estimates[name] for name in ("k", "k3", "c_x"))
    np.testing.assert_allclose(model.get_ydata(), _duffing_frequency(k, k3, amplitude),
                               rtol=1e-8)
    (zeta,) = damping.get_lines()
    # viscous damping on the small orbits: c / (2 omega), omega of the linearized model
    assert zeta.get_ydata()[0] == pytest.approx(c / (2 * np.sqrt(k)), rel=0.02)
    bands = [ax for ax in (frequency, damping)
             if any(isinstance(p, PolyCollection) for p in ax.collections)]
    assert bands == [frequency, damping]
    assert len(recorded) == 2                               # a marker series per decay
    # the curve reaches the largest recorded period's amplitude (under the first swing, 1)
    largest = max(max(line.get_xdata()) for line in recorded)
    assert amplitude.max() == pytest.approx(largest, rel=1e-12) and largest < 1.0
    for line in recorded:
        x, y = np.asarray(line.get_xdata()), np.asarray(line.get_ydata())
        assert len(x) >= 3 and x.max() <= 1.0
        np.testing.assert_allclose(y, _duffing_frequency(k, k3, x), rtol=0.03)
    assert frequency.get_ylabel() == "frequency [Hz]"
    assert damping.get_ylabel() == "damping ratio ζ [1]"
    assert damping.get_xlabel() == "amplitude of x [model units]"
    assert figure.get_suptitle().startswith("7. Backbone: data in memory")
    caption = figure.get_supxlabel().replace("\n", " ")
    assert "95% bands, by the delta method" in caption and "zero crossings" in caption
    _png(figure)


# --- the command line ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def report_file(tmp_path_factory, fit) -> Path:
    path = tmp_path_factory.mktemp("report") / "r.json"
    path.write_text(json.dumps(fit.to_dict()))
    return path


def _run(*args: str):
    return CliRunner().invoke(cli, list(args))


def test_plot_without_data_draws_panels_5_and_6_and_says_which_it_left_out(report_file,
                                                                            tmp_path):
    result = _run("plot", str(report_file), "-o", str(tmp_path / "fig.png"))
    assert result.exit_code == 0 and result.stdout == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig-5-parameters.png",
                                                           "fig-6-correlation.png"]
    assert result.stderr == ("left out panels 1 energy, 2 residuals, 3 phase, 4 motion: "
                             "they need the data the fit read (hamid plot RESULT.json "
                             "DATA..., or a fit in memory)\n")


def test_plot_with_data_writes_a_pdf_page_per_panel(report_file, tmp_path):
    result = _run("plot", str(report_file), str(SAMPLE), "-o", str(tmp_path / "fig.pdf"))
    assert result.exit_code == 0 and result.output == ""
    pdf = (tmp_path / "fig.pdf").read_bytes()
    assert len(re.findall(rb"/Type /Page\b", pdf)) == 6
    assert [p.name for p in tmp_path.iterdir()] == ["fig.pdf"]


def test_plot_of_one_panel_is_the_file_named(report_file, tmp_path):
    result = _run("plot", str(report_file), "-o", str(tmp_path / "p.svg"), "--panels", "5")
    assert result.exit_code == 0
    assert (tmp_path / "p.svg").read_text().startswith("<?xml")


def test_plot_draws_the_backbone_panel_from_a_report_alone(tmp_path, damped):
    report = tmp_path / "r.json"
    report.write_text(json.dumps(damped.to_dict()))
    result = _run("plot", str(report), "-o", str(tmp_path / "b.png"), "--panels", "backbone")
    assert result.exit_code == 0 and result.output == "", result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.png", "r.json"]
    assert imread(tmp_path / "b.png").shape[1] == 1200     # ten inches at 120 dots an inch


@pytest.mark.parametrize(("args", "message"), [
    (["-o", "fig.jpg"], "Error: -o 'fig.jpg': a figure is written as .png, .svg, .pdf"),
    (["-o", "fig.png", "--panels", "1"], "Error: panel 1 (energy) needs the data the fit read"),
    (["-o", "fig.png", "--panels", "0"], "Error: --panels: unknown panel '0'"),
])
def test_plot_usage_errors(report_file, tmp_path, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    result = _run("plot", str(report_file), *args)
    assert result.exit_code == 2 and result.stdout == ""
    assert message in result.stderr and "Traceback" not in result.output
    assert list(tmp_path.iterdir()) == []


def test_plot_refuses_other_data_than_the_fit_read(report_file, tmp_path, table):
    part = tmp_path / "part.csv"
    table[table.trajectory == 1].to_csv(part, index=False)
    result = _run("plot", str(report_file), str(part), "-o", str(tmp_path / "fig.png"))
    assert result.exit_code == 1 and result.stdout == ""
    assert result.stderr.startswith(f"Error: {part}: 801 samples in 1 trajectory, but the fit "
                                    "had 1602 in 2")
    assert [p.name for p in tmp_path.iterdir()] == ["part.csv"]


def test_fit_with_plot_writes_the_report_and_the_figures(tmp_path):
    result = _run("fit", str(SAMPLE), "--method", "joint", "-o", str(tmp_path / "r.json"),
                  "--plot", str(tmp_path / "f.png"))
    assert result.exit_code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "f-1-energy.png", "f-2-residuals.png", "f-3-phase.png", "f-5-parameters.png",
        "f-6-correlation.png", "r.json"]
    assert "left out panel 4 motion: it needs the trajectory refinement, which method joint " \
           "does not make" in result.stderr


def test_fit_with_a_bad_plot_name_fails_before_the_fit(tmp_path):
    result = _run("fit", str(SAMPLE), "-o", str(tmp_path / "r.json"), "--plot",
                  str(tmp_path / "f.gif"))
    assert result.exit_code == 2 and "--plot" in result.stderr and ".png" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_without_matplotlib_one_line_names_the_extra(tmp_path, report_file):
    code = ("import sys\nsys.modules['matplotlib'] = None\n"
            "from hamid.cli.app import main\nmain()")
    for args in (["plot", str(report_file), "-o", str(tmp_path / "f.png")],
                 ["fit", str(SAMPLE), "--plot", str(tmp_path / "f.png")]):
        out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True,
                             text=True)
        assert out.returncode == 1 and out.stdout == ""
        assert out.stderr == ("Error: drawing figures needs matplotlib: "
                              "pip install 'hamid[plot]'\n")
    assert list(tmp_path.iterdir()) == []


def test_plot_help_through_the_installed_command():
    out = subprocess.run([*hamid_command(), "plot", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "--panels" in out.stdout


def test_residuals_far_beyond_the_noise_are_drawn_on_their_own_scale():
    """The real double pendulum misses part of its friction: its residuals spread about 50
    times the noise band, shown against a normal of their own spread."""
    root = SAMPLE.parent
    result = hamid.fit(str(root / "double_pendulum.csv"), str(root / "double_pendulum.toml"),
                       method="joint", velocity="savgol")
    figure = figures.pages(result.to_dict(), result.recording, "residuals")[0][0][1]
    _, histogram, _ = _data_axes(figure)
    standard, own = histogram.get_lines()
    energies = fitted.energies(result.to_dict(), result.recording)
    z = energies.residual / energies.noise
    assert own.get_label() == f"N(0, {np.std(z):.3g}²)" and np.std(z) > 10
    assert histogram.get_ylim()[1] < 0.1 < standard.get_ydata().max()
    low, high = histogram.get_xlim()
    assert low <= np.percentile(z, 0.5) and high >= np.percentile(z, 99.5)


def test_parameters_known_to_rounding_get_short_tick_labels():
    """Clean data determine the estimates to 1e-13: the ticks are distances from a round
    number the row's title names, not 17-digit numbers running into each other, and no
    offset text ("1e−4+1.508") beside them."""
    result = hamid.fit(str(SAMPLE.parent / "peng_quadratic.csv"))
    figure = _page(result, "parameters")
    _png(figure)   # labels and offsets are set when drawn
    for ax in _data_axes(figure):
        labels = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
        assert labels and max(len(text) for text in labels) <= 6, labels
        assert not ax.xaxis.get_offset_text().get_text()
        name = ax.get_title(loc="left").split(" = ")[0]
        assert re.search(rf"; ticks: {re.escape(name)} − [-\d.e]+, in 10[⁻¹²³⁴⁵⁶⁷⁸⁹⁰]+$",
                         ax.get_title(loc="left")), ax.get_title(loc="left")
