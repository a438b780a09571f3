"""Figures fit for a paper (issue 38): every panel rendered at its default size, for a fit
of one degree of freedom (two trajectories) and for a fit of 15 decays of a damped beam read
from 15 files, and measured with matplotlib's own bounding boxes: no text beyond the figure,
no two texts (titles, axis and tick labels, legends, captions) overlapping."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import DRIVEN_DUFFING_MODEL

import hamid
from hamid.plot import figures

pytest.importorskip("matplotlib")

from matplotlib.axes import Axes  # noqa: E402
from matplotlib.collections import PathCollection  # noqa: E402
from matplotlib.legend import Legend  # noqa: E402
from matplotlib.text import Text  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
# Fifteen free decays of a damped hardening beam, in millimetres: amplitudes 2 to 16 mm.
BEAM = {"model": {"builtin": "duffing"}, "parameters": {"k": 40.0, "k3": 900.0},
        "damping": {"c_x": 0.15},
        "initial": [{"x": float(a), "v": 0.0} for a in np.linspace(0.002, 0.016, 15)],
        "simulate": {"t_end": 6.0, "dt": 0.005, "seed": 3},
        "noise": {"x": 2e-5, "v": 2e-4}}


@pytest.fixture(scope="module")
def one_dof() -> hamid.FitResult:
    return hamid.fit(str(ROOT / "sample_data" / "duffing.csv"))


@pytest.fixture(scope="module")
def beam(tmp_path_factory) -> hamid.FitResult:
    """The 15 decays, a file each (runs/decay_NN.csv, columns x_mm and v_mm_s)."""
    folder = tmp_path_factory.mktemp("beam") / "runs"
    folder.mkdir()
    frame = hamid.simulate(BEAM)
    for k, part in frame.groupby("trajectory"):
        part = part.drop(columns="trajectory").rename(columns={"x": "x_mm", "v": "v_mm_s"})
        part[["x_mm", "v_mm_s"]] *= 1e3
        part.to_csv(folder / f"decay_{k:02d}_at_the_free_end_of_the_beam.csv", index=False)
    return hamid.fit(sorted(str(p) for p in folder.iterdir()), model="duffing",
                     damping="viscous")


def _drawn_tick_labels(ax: Axes) -> set[int]:
    """The ids of the tick labels of `ax` left undrawn: their tick outside the view."""
    hidden = set()
    for axis in (ax.xaxis, ax.yaxis):
        low, high = sorted(axis.get_view_interval())
        slack = 1e-6 * (high - low)
        for tick in axis.get_major_ticks() + axis.get_minor_ticks():
            if not low - slack <= tick.get_loc() <= high + slack:
                hidden |= {id(tick.label1), id(tick.label2)}
    return hidden


def text_boxes(figure) -> list[tuple[str, object]]:
    """Every text drawn (its words, its box in pixels): a legend as one box."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(figure)   # the PNG backend: the boxes of a saved picture
    canvas.draw()
    renderer = canvas.get_renderer()
    hidden, boxes = set(), []
    for ax in figure.findobj(Axes):
        hidden |= _drawn_tick_labels(ax)
    for legend in figure.findobj(Legend):
        hidden |= {id(t) for t in legend.findobj(Text)}
        words = " / ".join(t.get_text() for t in legend.get_texts())
        boxes.append((f"legend [{words[:60]}]", legend.get_window_extent(renderer)))
    for text in figure.findobj(Text):
        if id(text) in hidden or not text.get_visible() or not text.get_text().strip():
            continue
        boxes.append((text.get_text(), text.get_window_extent(renderer)))
    return boxes


def layout_faults(figure) -> list[str]:
    """Texts beyond the figure's edges and pairs of texts that overlap (by more than a
    pixel each way)."""
    boxes = text_boxes(figure)
    width, height = figure.canvas.get_width_height()   # the Agg canvas of text_boxes
    faults = [f"{words!r} beyond the figure ({box})" for words, box in boxes
              if box.x0 < -1 or box.y0 < -1 or box.x1 > width + 1 or box.y1 > height + 1]
    for k, (a, box_a) in enumerate(boxes):
        for b, box_b in boxes[k + 1:]:
            overlap_x = min(box_a.x1, box_b.x1) - max(box_a.x0, box_b.x0)
            overlap_y = min(box_a.y1, box_b.y1) - max(box_a.y0, box_b.y0)
            if overlap_x > 1 and overlap_y > 1:
                faults.append(f"{a!r} overlaps {b!r}")
    return faults


def test_the_checker_finds_a_cut_title_and_overlapping_labels():
    """The checks can fail: a title wider than its figure, two labels on one spot."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(3, 2))
    ax = figure.add_subplot()
    figure.suptitle("a title much too long to fit in a figure three inches wide")
    ax.text(0.5, 0.5, "one")
    ax.text(0.5, 0.5, "two")
    faults = layout_faults(figure)
    assert any("beyond the figure" in f and "too long" in f for f in faults)
    assert any("'one' overlaps 'two'" in f for f in faults)


@pytest.mark.parametrize("panel", figures.PANELS)
@pytest.mark.parametrize("name", ["one_dof", "beam"])
def test_no_text_cut_or_overlapping(name, panel, request, tmp_path):
    fit = request.getfixturevalue(name)
    (drawn, figure), = figures.pages(fit.to_dict(), fit.recording, panel)[0]
    assert layout_faults(figure) == []


def _axes(figure) -> list:
    return [ax for ax in figure.findobj(Axes) if ax.get_label() != "<colorbar>"]


def _caption(figure) -> str:
    """The caption under a panel, on one line."""
    return figure.get_supxlabel().replace("\n", " ")


def _page(fit, panel: str):
    (_, figure), = figures.pages(fit.to_dict(), fit.recording, panel)[0]
    return figure


def test_axes_carry_the_units_the_data_were_converted_to(beam):
    """x_mm and v_mm_s were converted to m and m/s; E = v²/2 + ... has no parameter in
    its kinetic part, so energies are per unit mass, in m²/s²."""
    phase = _axes(_page(beam, "phase"))
    assert {ax.get_xlabel() for ax in phase} <= {"x [10⁻³ m]", "x [10⁻² m]"}
    assert {ax.get_ylabel() for ax in phase} <= {"v [10⁻² m/s]", "v [m/s]"}
    energy = _page(beam, "energy")
    assert "energy per unit mass" in {t.get_text() for t in energy.findobj(Text)}
    assert all(ax.get_ylabel() in ("E [10⁻⁵ m²/s²]", "E [10⁻⁴ m²/s²]", "E [10⁻³ m²/s²]")
               for ax in _axes(energy))
    assert _axes(energy)[-1].get_xlabel() == "t [s]"
    motion = _axes(_page(beam, "motion"))
    assert motion[0].get_ylabel() == "x [10⁻³ m]" and motion[-1].get_xlabel() == "t [s]"


def test_fifteen_decays_six_drawn_from_the_smallest_to_the_largest_and_said(beam):
    """Six of the 15 decays, spread over their levels (the amplitudes grow with the file
    number), the smallest and the largest among them; the caption says the choice."""
    figure = _page(beam, "energy")
    names = [ax.get_title(loc="left") for ax in _axes(figure)]
    assert len(names) == 6 and all(".csv" in n and "/" not in n for n in names)
    assert names[0].startswith("decay_01_") and names[-1].startswith("decay_15_")
    assert "6 of 15 trajectories shown, spread from the lowest energy level to the highest" \
        in _caption(figure)
    # the residuals of all 15 are drawn, a line each
    (series, *_), = [_axes(_page(beam, "residuals"))]
    assert len([line for line in series.get_lines() if len(line.get_xdata()) > 2]) == 15


def test_a_record_cut_by_dropouts_is_drawn_as_one(tmp_path):
    """One decay with three dropouts of 6 samples (single ones are just missing), fitted
    as four pieces (--gaps split): one row, one phase plot, its four pieces in it."""
    frame = hamid.simulate({**BEAM, "initial": BEAM["initial"][-1:]})
    for row in (200, 500, 800):
        frame.loc[row:row + 5, "x"] = np.nan
    path = tmp_path / "cut.csv"
    frame.to_csv(path, index=False)
    fit = hamid.fit(str(path), model="duffing", damping="viscous", gaps="split")
    assert len(fit.energy_levels) == 4
    energy = _page(fit, "energy")
    (ax,) = _axes(energy)
    assert ax.get_title(loc="left") == "trajectory 1"
    assert len([line for line in ax.get_lines() if line.get_linestyle() == "-"]) == 4
    assert "1 recording cut at dropouts or gaps drawn as one" in \
        _caption(energy)
    (phase,) = _axes(_page(fit, "phase"))
    (points,) = [c for c in phase.collections if isinstance(c, PathCollection)]
    assert len(points.get_offsets()) == len(frame) - 18




def test_the_motion_of_a_driven_fit_is_drawn_above_its_input(tmp_path):
    import tomllib

    model = tmp_path / "driven.toml"
    model.write_text(DRIVEN_DUFFING_MODEL)
    document = tomllib.loads(DRIVEN_DUFFING_MODEL)
    document["forcing"]["signals"] = {"F": {"kind": "multisine", "amplitude": 1.0,
                                            "band": [0.05, 1.0], "seed": 3}}
    frame = hamid.simulate({**document, "parameters": {"m": 1.5, "k": 4.0, "k3": 2.0},
                            "damping": {"c_x": 0.08}, "initial": [{"x": 0.0, "v": 0.0}],
                            "simulate": {"t_end": 40.0, "dt": 0.02},
                            "noise": {"x": 1e-3, "v": 1e-3}})
    fit = hamid.fit(frame, str(model), damping="viscous")
    figure = _page(fit, "motion")
    motion, misfit, driving = _axes(figure)
    assert driving.get_ylabel() == "input"
    (line,) = driving.get_lines()
    np.testing.assert_array_equal(line.get_xdata(), motion.get_lines()[0].get_xdata())
    shown = frame["t"] <= line.get_xdata()[-1] + 1e-9
    np.testing.assert_array_equal(line.get_ydata(), frame.loc[shown, "F"])
    assert "data in memory" in figure.get_suptitle() and "DataFrame" not in figure.get_suptitle()
    assert layout_faults(figure) == []
    backbone = _page(fit, "backbone")        # a driven record's periods are the drive's
    frequency, _ = _axes(backbone)
    assert len(frequency.get_lines()) == 1
    assert "the recording is driven: its periods are the drive's" in _caption(backbone)
