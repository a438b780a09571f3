"""The backbone's plots: frequency (Hz) and equivalent damping ratio against amplitude, the
band at the fit's level shaded and the recording's points overlaid, from a
``hamid.backbone/1`` report (`hamid.backbone.backbone_table`). Drawn into a figure of
their own (`hamid backbone -o`) or into panel 7 of the fit's pictures
(`hamid.plot.figures`), without pyplot."""

from __future__ import annotations

import textwrap
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from hamid.plot import labels
from hamid.plot.palette import colour

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure, SubFigure

__all__ = ["draw", "figure"]


def _band(ax: Axes, x: list[float], points: list[dict[str, Any]], key: str,
          shade: str, label: str) -> None:
    """Shade the band of `key` where both its ends are known."""
    import numpy as np

    low = np.array([np.nan if p[f"{key}_low"] is None else p[f"{key}_low"] for p in points])
    high = np.array([np.nan if p[f"{key}_high"] is None else p[f"{key}_high"]
                     for p in points])
    if np.isfinite(low).any():
        ax.fill_between(x, low, high, color=shade, alpha=0.25, linewidth=0, label=label)


def _caption(document: Mapping[str, Any]) -> str:
    """What the plots show and how: the curves, their bands, the recorded points."""
    modes = ", ".join(str(mode["mode"]) for mode in document["modes"])
    text = (f"Lines: the fitted model's conservative orbits (mode {modes}), frequency and "
            "equivalent damping ratio ΔE/(4πE) against amplitude (half the peak-to-peak "
            "range)")
    if document["bands"]:
        text += (f"; shaded: {100 * document['level']:g}% bands, by the delta method with "
                 "the fit's covariance")
    else:
        text += "; no bands: the report has no covariance"
    if document["data"]:
        text += "; points: the recording's periods between zero crossings"
        if len(document["modes"][0]["points"][0]["amplitude"]) > 1:
            text += (" (of several coordinates, they follow a mode's curve only where the "
                     "motion is mostly that mode)")
    stopped = [mode["stopped"] for mode in document["modes"] if mode.get("stopped")]
    if stopped:
        text += f"; the curve ends short of {stopped[0]}"
    return "; ".join([text, *document.get("notes", [])]) + "."


def draw(fig: Figure | SubFigure, document: Mapping[str, Any]) -> tuple[Axes, str]:
    """Frequency above and damping ratio below in `fig`; returns the upper axes, whose
    legend names every line, and the caption."""
    top, bottom = fig.subplots(2, 1, sharex=True)
    band = f"band at {100 * document['level']:g}%"
    for k, mode in enumerate(document["modes"]):
        q, shade = mode["coordinate"], colour(k)
        points = mode["points"]
        x = [p["amplitude"][q] for p in points]
        name = f"model, mode {mode['mode']}"
        top.plot(x, [p["frequency_hz"] for p in points], color=shade, label=name)
        _band(top, x, points, "frequency_hz", shade, f"{band}, mode {mode['mode']}")
        zeta = [p["damping_ratio"] for p in points]
        if any(z is not None for z in zeta):
            bottom.plot(x, [float("nan") if z is None else z for z in zeta], color=shade,
                        label=name)
            _band(bottom, x, points, "damping_ratio", shade, f"{band}, mode {mode['mode']}")
    for j, trajectory in enumerate(document["data"]):
        top.plot([p["amplitude"] for p in trajectory["points"]],
                 [p["frequency_hz"] for p in trajectory["points"]], "o", markersize=3,
                 color=colour(j + 1), alpha=0.8,
                 label=f"recorded, trajectory {labels.plain(trajectory['trajectory'])}")
    q = document["modes"][0]["coordinate"]
    unit = document["units"]["amplitude"].get(q)
    time = document["units"].get("time")
    top.set_ylabel("frequency [Hz]" if time in (None, "s") or time.endswith(" s")
                   else "frequency [1/time unit]")
    bottom.set_ylabel("damping ratio ζ [1]")
    bottom.set_xlabel(f"amplitude of {labels.plain(q)} [{unit or 'model units'}]")
    if not bottom.lines:
        bottom.text(0.5, 0.5, "no dissipation fitted", ha="center", va="center",
                    transform=bottom.transAxes)
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    return top, _caption(document)


def figure(document: Mapping[str, Any]) -> Figure:
    """The backbone as a figure of its own: its title, the two plots with their legends
    inside, and its caption below."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.0, 7.0), layout="constrained", dpi=120)
    top, caption = draw(fig, document)
    fig.suptitle(f"Backbone of model {labels.plain(document['model'])}")
    for ax in fig.axes:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize="small")
    fig.supxlabel(textwrap.fill(caption, 90), fontsize="small")
    return fig
