"""The backbone figure: frequency (Hz) and equivalent damping ratio against amplitude, the
band at the fit's level shaded and the recording's points overlaid, from a
``hamid.backbone/1`` report (`hamid.backbone.backbone_table`). Drawn without pyplot, like
the fit's panels (`hamid.plot.figures`)."""

from __future__ import annotations

import io
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from hamid.plot.figures import OKABE_ITO, check_output

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["check_output", "draw", "save"]


def _band(ax: Any, x: list[float], points: list[dict[str, Any]], key: str,
          colour: str) -> None:
    """Shade the band of `key` where both its ends are known."""
    import numpy as np

    low = np.array([np.nan if p[f"{key}_low"] is None else p[f"{key}_low"] for p in points])
    high = np.array([np.nan if p[f"{key}_high"] is None else p[f"{key}_high"]
                     for p in points])
    if np.isfinite(low).any():
        ax.fill_between(x, low, high, color=colour, alpha=0.25, linewidth=0,
                        label=f"{key.split('_')[0]} band")


def draw(document: Mapping[str, Any]) -> Figure:
    """The two panels of the backbone (frequency above, damping ratio below)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.0, 6.5), layout="constrained", dpi=120)
    top, bottom = fig.subplots(2, 1, sharex=True)
    level = f"{100 * document['level']:g}%"
    for k, mode in enumerate(document["modes"]):
        q, colour = mode["coordinate"], OKABE_ITO[k % len(OKABE_ITO)]
        points = mode["points"]
        x = [p["amplitude"][q] for p in points]
        top.plot(x, [p["frequency_hz"] for p in points], color=colour,
                 label=f"model, mode {mode['mode']}")
        _band(top, x, points, "frequency_hz", colour)
        zeta = [p["damping_ratio"] for p in points]
        if any(z is not None for z in zeta):
            bottom.plot(x, [float("nan") if z is None else z for z in zeta], color=colour,
                        label=f"model, mode {mode['mode']}")
            _band(bottom, x, points, "damping_ratio", colour)
    for j, trajectory in enumerate(document["data"]):
        top.plot([p["amplitude"] for p in trajectory["points"]],
                 [p["frequency_hz"] for p in trajectory["points"]], "o", markersize=3,
                 color=OKABE_ITO[(j + 1) % len(OKABE_ITO)], alpha=0.8,
                 label=f"recorded, trajectory {trajectory['trajectory']}")
    q = document["modes"][0]["coordinate"]
    unit = document["units"]["amplitude"].get(q)
    time = document["units"].get("time")
    top.set_ylabel("frequency (Hz)" if time in (None, "s") or time.endswith(" s")
                   else "frequency (1/time unit)")
    bottom.set_ylabel("equivalent damping ratio ζ (1)")
    bottom.set_xlabel(f"amplitude of {q} ({unit})" if unit
                      else f"amplitude of {q} (model units)")
    stopped = any(mode.get("stopped") for mode in document["modes"])
    top.set_title(f"Backbone of model {document['model']}"
                  + (f", bands at {level}" if document["bands"] else ", no covariance")
                  + ("\n(ends short of an internal resonance)" if stopped else ""))
    top.legend(fontsize="small")
    if bottom.lines:
        bottom.legend(fontsize="small")
    else:
        bottom.text(0.5, 0.5, "no dissipation fitted", ha="center", va="center",
                    transform=bottom.transAxes)
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    return fig


def save(document: Mapping[str, Any], path: str) -> None:
    """Draw the figure and write it (PNG, SVG or PDF by the extension), atomically."""
    from hamid.data import writing

    check_output(path)
    extension = os.path.splitext(path)[1].lower()
    buffer = io.BytesIO()
    metadata = {".pdf": {"CreationDate": None}, ".svg": {"Date": None}}.get(extension)
    draw(document).savefig(buffer, format=extension[1:], metadata=metadata)
    writing.write_bytes(buffer.getvalue(), path)
