"""Figures fit for a paper (issue 38): every panel rendered at its default size, for a fit
of one degree of freedom (two trajectories) and for a fit of 15 decays of a damped beam read
from 15 files, and measured with matplotlib's own bounding boxes: no text beyond the figure,
no two texts (titles, axis and tick labels, legends, captions) overlapping."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import hamid
from hamid.plot import figures

pytest.importorskip("matplotlib")

from matplotlib.axes import Axes  # noqa: E402
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
