"""The fit's pictures: six panels drawn with matplotlib (the optional extra ``hamid[plot]``).

1. ``energy``: the fitted energy over time per trajectory, against its level h (h minus
   the work dissipated so far, with damping) and the band the measurement noise puts
   around it;
2. ``residuals``: the energy residuals over time, their histogram in units of the noise
   band against the standard normal density, and their autocorrelation;
3. ``phase``: the phase portrait of each coordinate, coloured by residual, inside the
   fitted energy's contour at each trajectory's level;
4. ``motion``: recorded against fitted motion over one refinement segment per trajectory;
5. ``parameters``: the estimates with their confidence intervals (and the truth, when the
   data carry it);
6. ``correlation``: the correlation matrix of the estimates;
7. ``backbone``: the fitted model's backbone, frequency and damping ratio against amplitude
   with their bands, and the recording's own points (`hamid.plot.backbone_figure`); drawn
   only when asked for, as its orbits take up to a minute for several coordinates.

Panels 1-4 need the records (`hamid.data.records.Recording`), panel 4 the trajectory
refinement; 5, 6 and 7 need only the report (7 overlays the records of free decays).
Figures are made without pyplot, so no window ever opens and no backend is chosen: headless
wherever it runs.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from hamid.data import column_roles
from hamid.data.records import Recording
from hamid.errors import DataError, HamidError, UsageError
from hamid.plot import backbone_figure, fitted, labels
from hamid.plot.palette import OKABE_ITO, colour

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure, SubFigure

__all__ = ["DEFAULT_PANELS", "FORMATS", "PANELS", "check_output", "choose", "figure",
           "output_paths", "pages", "panel_files", "parse_panels", "save", "write_pages"]

PANELS = ("energy", "residuals", "phase", "motion", "parameters", "correlation", "backbone")
DEFAULT_PANELS = PANELS[:6]   # all that apply of these when none are asked for
FORMATS = (".png", ".svg", ".pdf")
_TITLES = {"energy": "Energy over time", "residuals": "Energy residuals",
           "phase": "Phase portraits", "motion": "Recorded and fitted motion",
           "parameters": "Parameters", "correlation": "Correlation of the estimates",
           "backbone": "Backbone"}
_RESIDUAL_MAP = "berlin"     # diverging, dark at zero: visible on white, colour-blind safe
_CORRELATION_MAP = "RdBu_r"  # ColorBrewer's diverging map, colour-blind safe
MAX_SHOWN = 6                # trajectories drawn one by one; later ones are left out
MAX_POINTS = 20_000          # samples drawn per series; longer ones are thinned evenly
# Parameters a panel shows: a row each in panel 5 (302 rows took 103 s and 461 MB), a row
# and a column of panel 6's matrix.
MAX_PARAMETERS = {"parameters": 40, "correlation": 200}
_WIDTH = 10.0                # inches
_DPI = 120
_TITLE_WIDTH = 95            # characters of a title's line at the default width


def _matplotlib() -> Any:
    """matplotlib's Figure class, or a one-line error naming the extra to install."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise HamidError("drawing figures needs matplotlib: pip install 'hamid[plot]'") \
            from exc
    return Figure


def parse_panels(panels: str | int | Sequence[str | int] | None) -> tuple[str, ...] | None:
    """Panel names from numbers (1 to the number of `PANELS`) or names, a comma list or a
    sequence; None for the default ones that apply."""
    if panels is None:
        return None
    items = panels.split(",") if isinstance(panels, str) else \
        [panels] if isinstance(panels, int) else list(panels)
    names = []
    for item in items:
        text = str(item).strip().lower()
        name = (PANELS[int(text) - 1] if text in {str(k) for k in range(1, len(PANELS) + 1)}
                else text)
        if name not in PANELS:
            listed = ", ".join(f"{k} {p}" for k, p in enumerate(PANELS, 1))
            raise UsageError(f"--panels: unknown panel {str(item)!r} (choose from {listed})")
        names.append(name)
    return tuple(dict.fromkeys(names))


def _obstacle(panel: str, report: Mapping[str, Any],
              recording: Recording | None) -> str | None:
    """What a panel needs that is missing, or None."""
    if panel in PANELS[:4] and recording is None:
        return ("the data the fit read (hamid plot RESULT.json DATA..., or a fit in "
                "memory)")
    refinement = report["method"].get("refinement") or {}
    if panel == "motion" and not refinement.get("applied"):
        return "the trajectory refinement, which " + (
            f"did not run ({refinement['reason']})" if refinement.get("reason")
            else f"method {report['method']['kind']} does not make")
    covariance = report.get("covariance") or {}
    if panel == "correlation" and len(covariance.get("names", [])) < 2:
        return "the covariance of at least two free parameters"
    shown = {"parameters": len(report["parameters"]),
             "correlation": len(covariance.get("names", []))}.get(panel, 0)
    if shown > MAX_PARAMETERS.get(panel, shown):
        return (f"at most {MAX_PARAMETERS[panel]} parameters to show (the report has "
                f"{shown:,})")
    return None


def _check_parameters(report: Mapping[str, Any]) -> None:
    """Each estimate inside its interval and its axis within the doubles, before drawing:
    a report edited by hand gave matplotlib's "'xerr' must not contain negative values"
    and "Axis limits cannot be NaN or Inf"."""
    for p in report["parameters"]:
        name, estimate = labels.plain(p["name"]), p["estimate"]
        low, high = p["ci_low"], p["ci_high"]
        if low is not None and high is not None and not low <= estimate <= high:
            raise DataError(f"parameter {name}: estimate {estimate:.6g} lies outside its "
                            f"interval [{low:.6g}, {high:.6g}]; was the report edited?")
        reach = _reach(estimate, low, high, p["truth"])
        if not math.isfinite(estimate - reach) or not math.isfinite(estimate + reach):
            raise DataError(f"parameter {name}: estimate {estimate:.6g} and its interval "
                            "are too large to draw (the axis would pass the largest double)")


def _reach(estimate: float, *around: float | None) -> float:
    """Half a parameter's axis: the estimate in the middle, the values `around` it in
    view."""
    known = [abs(x - estimate) for x in around if x is not None]
    return 1.3 * max(known, default=0.0) or 0.1 * abs(estimate) or 1.0


def choose(report: Mapping[str, Any], recording: Recording | None,
           panels: str | int | Sequence[str | int] | None = None
           ) -> tuple[tuple[str, ...], list[str]]:
    """The panels to draw, and a note on those left out (one per reason): by default all
    of `DEFAULT_PANELS` that apply; a panel asked for that cannot be drawn is an error."""
    asked = parse_panels(panels)
    drawn, left_out = [], {}
    for k, panel in enumerate(PANELS, 1):
        if panel not in (DEFAULT_PANELS if asked is None else asked):
            continue
        obstacle = _obstacle(panel, report, recording)
        if obstacle is None:
            drawn.append(panel)
        elif asked is not None:
            raise UsageError(f"panel {k} ({panel}) needs {obstacle}")
        else:
            left_out.setdefault(obstacle, []).append(f"{k} {panel}")
    if "parameters" in drawn:
        _check_parameters(report)
    notes = [f"left out panel{'s' if len(names) > 1 else ''} {', '.join(names)}: "
             f"{'they need' if len(names) > 1 else 'it needs'} {obstacle}"
             for obstacle, names in left_out.items()]
    if not drawn:
        raise UsageError("no panel to draw: " + "; ".join(notes))
    return tuple(drawn), notes


@dataclass(frozen=True)
class _Context:
    """What every panel reads: the report, the records, and the numbers worked out once."""

    report: Mapping[str, Any]
    recording: Recording | None

    @cached_property
    def energies(self) -> fitted.Energies:
        assert self.recording is not None
        return fitted.energies(self.report, self.recording)

    @cached_property
    def backbone(self) -> dict[str, Any]:
        """The ``hamid.backbone/1`` report of the fitted model at its default amplitudes
        (mode 1), with the recording's points."""
        from hamid.backbone import backbone_table

        return backbone_table.backbone_report(
            backbone_table.Source.of_report(self.report), backbone_table.Request(),
            records=None if self.recording is None else self.recording.records,
            names=[labels.source_name(s) for s in self.report["data"]["sources"]])

    @cached_property
    def records(self) -> list[tuple[str, list[int]]]:
        """Each recording's name and its fitted trajectories (`labels.recordings`)."""
        return labels.recordings([str(level["trajectory"])
                                  for level in self.report["energy_levels"]])

    def spread(self, most: int) -> list[int]:
        """At most `most` recordings, all when there are no more, else spread evenly from
        the lowest energy level to the highest (their first trajectory's h), in order."""
        n = len(self.records)
        if n <= most:
            return list(range(n))
        h = [self.report["energy_levels"][pieces[0]]["h"] for _, pieces in self.records]
        by_level = np.argsort(h, kind="stable")
        return sorted(int(by_level[k]) for k in np.linspace(0, n - 1, most).round().astype(int))

    @property
    def shown(self) -> list[int]:
        """The recordings drawn one by one."""
        return self.spread(MAX_SHOWN)

    def shown_note(self, shown: Sequence[int]) -> str:
        """Said in a caption when recordings were left out, or pieces joined."""
        n, kind = len(self.records), self.kind
        cut = sum(len(pieces) > 1 for _, pieces in self.records)
        joined = (f"; {cut} recording{'s' if cut > 1 else ''} cut at dropouts or gaps drawn "
                  "as one, each piece fitted with its own level" if cut else "")
        if len(shown) == n:
            return joined
        return (f"; {len(shown)} of {n} {kind} shown, spread from the lowest energy level to "
                f"the highest{joined}")

    @property
    def kind(self) -> str:
        """What the recordings are called: trajectories, or recordings when one was cut."""
        return ("recordings" if len(self.records) < len(self.report["energy_levels"])
                else "trajectories")

    @property
    def damped(self) -> bool:
        """Whether the fit had dissipation: --damping, or the model's own function."""
        return bool(self.report["method"]["damping"] or self.report["model"].get("dissipation"))

    @property
    def time_label(self) -> str:
        return "t [s]" if self.report["data"].get("time") else "sample"

    def rows(self, j: int) -> slice:
        start, stop = self.recording.records.bounds()[j]  # type: ignore[union-attr]
        return slice(start, stop)

    def unit(self, name: str) -> str | None:
        """A model variable's SI unit (m, rad, m/s, rad/s) when its column named one."""
        column = self.report["data"]["columns"].get(name, name)
        unit = column_roles.column_scale(column)[1]
        if unit is None:
            return None
        base = "rad" if unit.removesuffix("_s") in ("rad", "mrad", "deg") else "m"
        return f"{base}/s" if unit.endswith("_s") else base

    def label(self, name: str) -> str:
        """A model variable's axis label, with its SI unit when its column named one."""
        unit = self.unit(name)
        return name if unit is None else f"{name} [{unit}]"

    @property
    def coordinate_unit(self) -> str | None:
        """The unit all coordinates share, if they share one."""
        assert self.recording is not None
        units = {self.unit(name) for name in self.recording.model.coordinates}
        return units.pop() if len(units) == 1 else None

    @property
    def per_unit_mass(self) -> bool:
        """Whether the energy's parameter-free part (a unit-mass kinetic energy) sets its
        scale, so that energies are per unit mass (docs/output.md, method.scale)."""
        return (self.report["method"].get("scale") or {}).get("source") == "energy"

    def energy_name(self, what: str) -> str:
        """An energy axis's name: per unit mass when so."""
        return f"{what} per unit mass" if self.per_unit_mass else what

    @property
    def energy_unit(self) -> str | None:
        """The unit of an energy per unit mass, (m/s)² or (rad/s)², when the coordinates
        share a unit; else none is known (an input's work is in units the data do not
        name)."""
        unit = self.coordinate_unit if self.per_unit_mass else None
        return f"{unit}²/s²" if unit else None

    def title(self, panel: str) -> str:
        """The panel's title: what it shows, the files and the method, wrapped to fit."""
        import textwrap

        report = self.report
        sources = [labels.source_name(s) for s in report["data"]["sources"]]
        files = ", ".join(sources[:2]) + (f" and {len(sources) - 2} more"
                                          if len(sources) > 2 else "")
        method = report["method"]
        refined = (method.get("refinement") or {}).get("applied")
        return textwrap.fill(f"{PANELS.index(panel) + 1}. {_TITLES[panel]}: {files or 'data'} "
                             f"— {labels.plain(report['model']['name'])}, method {method['kind']}"
                             f"{' + trajectory refinement' if refined else ''}", _TITLE_WIDTH)


def _middle(fig: Figure | SubFigure) -> Any:
    """The middle of three columns of a panel: room for a square plot and its colour bar."""
    return fig.add_gridspec(1, 3, width_ratios=(1, 1.6, 1))[0, 1]


def _thin(n: int) -> slice:
    """Every k-th of n samples, so that at most MAX_POINTS are drawn."""
    return slice(None, None, max(1, -(-n // MAX_POINTS)))


@dataclass(frozen=True)
class _Drawn:
    """What a panel drew: its caption, and the axes whose legend goes in a row above it
    (entries of at most `longest` characters)."""

    caption: str
    legend: Axes | None = None
    longest: int = 12


def _legend_row(head: SubFigure, drawn: _Drawn) -> float:
    """The legend of a panel in `head`, the strip between its title and its plots (a
    figure legend "outside" ran into the title); returns the strip's height in inches."""
    if drawn.legend is None:
        return 0.05
    handles, names = drawn.legend.get_legend_handles_labels()
    columns = max(1, min(len(names), 4, 100 // (drawn.longest + 8)))
    head.legend(handles, names, loc="center", ncols=columns, frameon=False, fontsize="small")
    return 0.1 + 0.22 * -(-len(names) // columns)


def _draw_energy(fig: Figure | SubFigure, ctx: _Context) -> str:
    e = ctx.energies
    shown = ctx.shown
    axes = fig.subplots(len(shown), 1, sharex=True, squeeze=False)[:, 0]
    for ax, k in zip(axes, shown, strict=True):
        name, pieces = ctx.records[k]
        for n, j in enumerate(pieces):
            rows = ctx.rows(j)
            step = _thin(rows.stop - rows.start)
            t, level, band = e.time[rows][step], e.level[rows][step], 2 * e.noise[rows][step]
            ax.fill_between(t, level - band, level + band, color=OKABE_ITO[5], alpha=0.35,
                            linewidth=0, label="_" * n + "±2σ of the measurement noise")
            ax.plot(t, e.energy[rows][step], color=OKABE_ITO[0], linewidth=0.9,
                    label="_" * n + "E(q, v; θ) at the fitted θ")
            ax.plot(t, level, color="black", linestyle="--", linewidth=1.2,
                    label="_" * n + ("h − dissipated work" if ctx.damped else
                                     "mean energy (weak rows fit no level)"
                                     if ctx.report["method"]["kind"] == "weak"
                                     else "fitted level h"))
        ax.set_title(name, fontsize="small", loc="left")
        labels.label_axis(ax, "y", "E", ctx.energy_unit)
    axes[-1].set_xlabel(ctx.time_label)
    fig.supylabel(ctx.energy_name("energy"), fontsize="medium")
    return _Drawn("the band is twice the standard deviation the measurement noise puts into "
                  f"E at each sample{ctx.shown_note(shown)}", axes[0], 30)


def _autocorrelation(residual: np.ndarray, bounds: list[tuple[int, int]],
                     lags: int) -> np.ndarray:
    """Sum of r_i r_(i+k) over pairs within a trajectory, over the sum of r²: the
    report's lag-1 autocorrelation, at lags 0..lags."""
    total = float(residual @ residual)
    pairs = np.zeros(lags + 1)
    for start, stop in bounds:
        r = residual[start:stop]
        for k in range(min(lags + 1, len(r))):
            pairs[k] += float(r[:len(r) - k] @ r[k:])
    return pairs / total if total > 0 else pairs


def _draw_residuals(fig: Figure | SubFigure, ctx: _Context) -> str:
    e = ctx.energies
    series, histogram, correlation = fig.subplots(1, 3, width_ratios=(2.2, 1, 1))
    listed = len(ctx.records) <= MAX_SHOWN
    for k, (name, pieces) in enumerate(ctx.records):
        for n, j in enumerate(pieces):
            rows = ctx.rows(j)
            step = _thin(rows.stop - rows.start)
            series.plot(e.time[rows][step], e.residual[rows][step], color=colour(k),
                        linewidth=0.7, alpha=1.0 if listed else 0.6,
                        label=name if listed and n == 0 else "_")
    series.axhline(0.0, color="grey", linewidth=0.8)
    series.set_xlabel(ctx.time_label)
    labels.label_axis(series, "y", ctx.energy_name("energy residual r"), ctx.energy_unit)
    r = e.residual
    # in units of the noise band: N(0, 1) when the model is right and the noise is white
    z = r[e.noise > 0] / e.noise[e.noise > 0]
    # the bulk of the residuals, however far a few outliers reach
    low, high = np.percentile(z, [0.5, 99.5]) if z.size else (0.0, 0.0)
    span = (min(low, -4.0), max(high, 4.0))
    heights, _, _ = histogram.hist(z, bins=min(60, max(10, int(np.sqrt(len(z))))),
                                   range=span, density=True, color=OKABE_ITO[0], alpha=0.6,
                                   label="r / σ")
    x = np.linspace(*span, 200)
    histogram.plot(x, np.exp(-x**2 / 2) / np.sqrt(2 * np.pi), color=OKABE_ITO[3],
                   linewidth=1.5, label="N(0, 1)")
    spread = float(np.std(z)) if z.size else 1.0
    if not 0.5 < spread < 2.0:   # misfit beyond the noise: the residuals' own scale too
        histogram.plot(x, np.exp(-(x / spread)**2 / 2) / (spread * np.sqrt(2 * np.pi)),
                       color=OKABE_ITO[5], linewidth=1.2, linestyle="--",
                       label=f"N(0, {spread:.3g}²)")
        # scaled to the residuals: the standard normal's peak runs off the top
        histogram.set_ylim(0.0, max(heights.max(initial=0.0),
                                    1 / (spread * np.sqrt(2 * np.pi))))
    histogram.set(xlabel="r / σ", ylabel="density", title="histogram")
    histogram.legend(fontsize="x-small", loc="upper left", frameon=False, handlelength=1.2)
    histogram.set_ylim(top=1.45 * histogram.get_ylim()[1])   # room for the legend
    histogram.xaxis.set_major_locator(labels.ticks(3))
    bounds = ctx.recording.records.bounds()  # type: ignore[union-attr]
    lags = max(1, min(40, min(stop - start for start, stop in bounds) // 4))
    # lag 0 is 1 by definition: from lag 1 on, the scale shows what matters
    correlation.bar(np.arange(1, lags + 1), _autocorrelation(r, bounds, lags)[1:],
                    color=OKABE_ITO[2], width=0.8)
    limit = 1.96 / np.sqrt(len(r))
    correlation.axhspan(-limit, limit, color="grey", alpha=0.25, linewidth=0)
    correlation.axhline(0.0, color="grey", linewidth=0.8)
    correlation.set(xlabel="lag [samples]", title="autocorrelation")
    labels.label_axis(correlation, "y", "autocorrelation")
    every = "" if listed else f"; all {len(ctx.records)} {ctx.kind}, a colour each"
    return _Drawn(f"r = E(q, v; θ) − h{' + the dissipated work' if ctx.damped else ''}; σ: "
                  "the standard deviation the measurement noise puts into E (the energy "
                  "panel's band); autocorrelation over pairs within trajectories, grey: the "
                  f"95% band of white noise{every}", series if listed else None,
                  max(len(name) for name, _ in ctx.records))


def _phase_cells(n_records: int, n_coordinates: int) -> tuple[int, int, list[list[int]]]:
    """The phase panel's grid: rows, columns and the cell of each (recording, coordinate),
    a recording's coordinates side by side (wrapped at three), one degree of freedom's
    recordings three to a row."""
    if n_coordinates == 1:
        columns = min(3, n_records)
        return -(-n_records // columns), columns, [[k] for k in range(n_records)]
    columns = min(n_coordinates, 3)
    per_record = -(-n_coordinates // columns)
    cells = [[k * per_record * columns + i for i in range(n_coordinates)]
             for k in range(n_records)]
    return n_records * per_record, columns, cells


def _phase_shown(ctx: _Context) -> list[int]:
    """The recordings the phase panel draws: six plots' worth, at least two."""
    n = len(ctx.recording.model.coordinates)  # type: ignore[union-attr]
    return ctx.spread(max(2, MAX_SHOWN // n))


def _draw_phase(fig: Figure | SubFigure, ctx: _Context) -> str:
    from matplotlib.colors import Normalize

    model, records = ctx.recording.model, ctx.recording.records  # type: ignore[union-attr]
    e = ctx.energies
    N = len(model.coordinates)
    shown = _phase_shown(ctx)
    n_rows, columns, cells = _phase_cells(len(shown), N)
    axes = fig.subplots(n_rows, columns, squeeze=False).ravel()
    every = np.concatenate([np.arange(ctx.rows(j).start, ctx.rows(j).stop)
                            for k in shown for j in ctx.records[k][1]])
    scale = float(np.quantile(np.abs(e.residual[every]), 0.99)) or 1.0
    norm = Normalize(-scale, scale)
    h = [level["h"] for level in ctx.report["energy_levels"]]
    points = None
    for kk, k in enumerate(shown):
        name, pieces = ctx.records[k]
        rows = np.concatenate([np.arange(ctx.rows(j).start, ctx.rows(j).stop)
                               for j in pieces])
        step = _thin(len(rows))
        for i in range(N):
            ax = axes[cells[kk][i]]
            q, v = records.X[rows, i], records.X[rows, N + i]
            points = ax.scatter(q[step], v[step], c=e.residual[rows][step],
                                cmap=_RESIDUAL_MAP, norm=norm, s=3, linewidths=0, zorder=2)
            margin_q, margin_v = 0.12 * np.ptp(q) or 1.0, 0.12 * np.ptp(v) or 1.0
            grid_q = np.linspace(q.min() - margin_q, q.max() + margin_q, 100)
            grid_v = np.linspace(v.min() - margin_v, v.max() + margin_v, 100)
            lowest = fitted.lowest_energy(ctx.report, ctx.recording,  # type: ignore[arg-type]
                                          i, pieces[0], grid_q, grid_v)
            # above the points; solid whatever the sign (matplotlib dashes negative levels)
            ax.contour(grid_q, grid_v, lowest, levels=[h[pieces[0]]], colors=[OKABE_ITO[1]],
                       linewidths=1.6, linestyles="solid", zorder=3)
            ax.set_title(name, fontsize="small", loc="left")
            ax.xaxis.set_major_locator(labels.ticks(4))
            labels.label_axis(ax, "x", model.coordinates[i], ctx.unit(model.coordinates[i]))
            labels.label_axis(ax, "y", model.velocities[i], ctx.unit(model.velocities[i]))
    used = {cell for row in cells for cell in row}
    for c, ax in enumerate(axes):
        if c not in used:
            ax.set_axis_off()
    axes[0].plot([], [], color=OKABE_ITO[1], linewidth=1.6,
                 label="E = h, the fitted level" + (" at the start" if ctx.damped else ""))
    bar = fig.colorbar(points, ax=[axes[c] for c in sorted(used)], shrink=0.9)
    labels.label_axis(bar.ax, "y", ctx.energy_name("energy residual r"), ctx.energy_unit)
    return _Drawn("points: the samples, coloured by their energy residual; line: "
                  + ("E = h" if N == 1 else
                     "where E reaches the level h, the other coordinates as recorded and their "
                     "velocities at rest (the bound of the motion at that level)")
                  + ("; with damping, h is the energy at the start" if ctx.damped else "")
                  + ctx.shown_note(shown), axes[0], 40)


def _draw_motion(fig: Figure | SubFigure, ctx: _Context) -> str:
    model, records = ctx.recording.model, ctx.recording.records  # type: ignore[union-attr]
    shown, driven = ctx.shown, bool(model.inputs)
    ratios = [3, 1.4, 1.4] if driven else [3, 1.4]
    axes = fig.subplots(len(ratios) * len(shown), 1, height_ratios=ratios * len(shown),
                        squeeze=False)[:, 0]
    unit = ctx.coordinate_unit
    seconds = fitted.segment_seconds(ctx.report)
    recorded_position = ctx.recording.compared[1]  # type: ignore[union-attr]
    for kk, k in enumerate(shown):
        name, pieces = ctx.records[k]
        motion, misfit = axes[len(ratios) * kk], axes[len(ratios) * kk + 1]
        for n, j in enumerate(pieces):
            segment = fitted.segment_motion(ctx.report, ctx.recording,  # type: ignore[arg-type]
                                            j)
            step = _thin(len(segment.t))
            t = segment.t[step]
            for i, coordinate in enumerate(model.coordinates):
                recorded, integrated = segment.recorded[step, i], segment.model[step, i]
                motion.plot(t, recorded, linestyle="none", marker="o", markersize=2,
                            alpha=0.45, color=colour(i), zorder=2,
                            label="_" * n + f"{coordinate} " + (
                                "recorded" if recorded_position[i] else "reconstructed"))
                motion.plot(t, integrated, color=colour(i), linewidth=1.4, zorder=3,
                            label="_" * n + f"{coordinate} fitted model")
                misfit.plot(t, recorded - integrated, color=colour(i), linewidth=0.7)
            if driven:
                rows = slice(*records.bounds()[j])
                for u, input_name in enumerate(model.inputs):
                    axes[3 * kk + 2].plot(records.t[rows][step], records.U[rows, u][step],
                                          color=colour(len(model.coordinates) + u),
                                          linewidth=0.8, label="_" * n + f"{input_name} input")
        motion.set_title(name, fontsize="small", loc="left")
        labels.label_axis(motion, "y", model.coordinates[0] if len(model.coordinates) == 1
                          else "q", unit)
        misfit.axhline(0.0, color="grey", linewidth=0.8)
        labels.label_axis(misfit, "y", "misfit\n", unit)
        misfit.yaxis.label.set_fontsize("small")
        below = axes[len(ratios) * kk + len(ratios) - 1]
        for ax in axes[len(ratios) * kk:len(ratios) * kk + len(ratios) - 1]:
            ax.sharex(below)
            ax.tick_params(labelbottom=False)
        if driven:
            labels.label_axis(below, "y", "input")
            below.yaxis.label.set_fontsize("small")
    axes[-1].set_xlabel(ctx.time_label)
    if driven:
        for handle, label in zip(*axes[2].get_legend_handles_labels(), strict=True):
            axes[0].plot([], [], color=handle.get_color(), label=label)
    length = f"its first {seconds:.3g} s" if seconds is not None else "the whole record"
    rebuilt = ("; positions not recorded are shown as reconstructed (integrated from the "
               "recorded channels, less their cycle means), which the fit did not compare"
               if not recorded_position[:len(model.coordinates)].all() else "")
    return _Drawn(f"each trajectory over the refinement's longest segment ({length}), the "
                  "fitted model integrated from its best-fitting initial state; misfit: "
                  f"recorded − model{rebuilt}"
                  f"{ctx.shown_note(shown)}", axes[0], 20)


def _draw_parameters(fig: Figure | SubFigure, ctx: _Context) -> str:
    from matplotlib.ticker import FuncFormatter

    parameters = ctx.report["parameters"]
    level = ctx.report["method"]["level"]
    axes = fig.subplots(len(parameters), 1, squeeze=False)[:, 0]
    for ax, p in zip(axes, parameters, strict=True):
        name = labels.plain(p["name"])
        estimate, low, high, truth = p["estimate"], p["ci_low"], p["ci_high"], p["truth"]
        text = f"{name} = {estimate:.6g}"
        if low is not None and high is not None:
            ax.errorbar([estimate], [0], xerr=[[estimate - low], [high - estimate]],
                        fmt="o", color=OKABE_ITO[0], capsize=4, markersize=5)
            text += f" ± {p['stderr']:.2g} (standard error)" if p["stderr"] else ""
        else:
            ax.plot([estimate], [0], marker="D" if p["fixed"] else "o", color=OKABE_ITO[0])
            text += " (fixed)" if p["fixed"] else " (no standard error)"
        # the interval in the middle, the truth in view
        reach = _reach(estimate, low, high, truth)
        ax.set_xlim(estimate - reach, estimate + reach)
        if truth is not None:
            ax.axvline(truth, color=OKABE_ITO[3], linestyle="--", linewidth=1.3)
            text += f"; truth {truth:.6g}"
        ax.set_yticks([])
        ax.xaxis.set_major_locator(labels.ticks(7))
        power = int(np.floor(np.log10(reach)))
        if reach < 1e-3 * abs(estimate):
            # ticks as distances from a round number near the estimate, said in the title
            centre = float(np.round(estimate, -power - 1))
            ax.xaxis.set_major_formatter(FuncFormatter(
                lambda x, _, c=centre, p=power:
                labels.number(round((x - c) / 10.0**p, 3) + 0.0, 4)))
            text += f"; ticks: {name} − {centre:.10g}, in {labels.power_text(power)}"
        else:
            labels.label_axis(ax, "x", "")
            scaled = ax.get_xlabel()
            if scaled:
                ax.set_xlabel("")
                text += f"; ticks in {scaled.strip('[] ')}"
        ax.set_title(text, fontsize="medium", loc="left")
    axes[-1].set_xlabel("estimate")
    truth = ", dashed: the truth" if any(p["truth"] is not None for p in parameters) else ""
    return _Drawn(f"bars: {100 * level:g}% confidence intervals{truth}; each row on its own "
                  "scale")


def _draw_correlation(fig: Figure | SubFigure, ctx: _Context) -> str:
    covariance = ctx.report["covariance"]
    names = [labels.plain(name) for name in covariance["names"]]
    matrix = np.array([[np.nan if x is None else x for x in row]
                       for row in covariance["matrix"]], dtype=float)
    sd = np.sqrt(np.diag(matrix))
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = matrix / np.outer(sd, sd)
    ax = fig.add_subplot(_middle(fig))
    image = ax.imshow(correlation, cmap=_CORRELATION_MAP, vmin=-1, vmax=1)
    ax.set_xticks(range(len(names)), names, rotation=45 if len(names) > 6 else 0)
    ax.set_yticks(range(len(names)), names)
    ax.set(xlabel="parameter", ylabel="parameter")
    if len(names) <= 12:
        for (a, b), value in np.ndenumerate(correlation):
            ax.text(b, a, "—" if np.isnan(value) else f"{value:+.2f}", ha="center",
                    va="center", color="white" if abs(value) > 0.6 else "black",
                    fontsize="small")
    fig.colorbar(image, ax=ax, label="correlation")
    return _Drawn("the correlations of the free parameters' estimates, from their covariance")


def _draw_backbone(fig: Figure | SubFigure, ctx: _Context) -> _Drawn:
    top, caption = backbone_figure.draw(fig, ctx.backbone)
    return _Drawn(caption, top, longest=30)


_DRAW: dict[str, Callable[[Any, _Context], _Drawn]] = {
    "energy": _draw_energy, "residuals": _draw_residuals, "phase": _draw_phase,
    "motion": _draw_motion, "parameters": _draw_parameters, "correlation": _draw_correlation,
    "backbone": _draw_backbone,
}


def _height(panel: str, ctx: _Context) -> float:
    """The panel's height in inches, for its number of rows."""
    if panel == "energy":
        return 1.2 + 2.0 * len(ctx.shown)
    if panel == "motion":
        driven = bool(ctx.recording.model.inputs)  # type: ignore[union-attr]
        return 1.2 + (3.4 if driven else 2.8) * len(ctx.shown)
    if panel == "phase":
        n = len(ctx.recording.model.coordinates)  # type: ignore[union-attr]
        return 1.4 + 3.2 * _phase_cells(len(_phase_shown(ctx)), n)[0]
    if panel == "parameters":
        return 1.0 + 0.85 * len(ctx.report["parameters"])
    if panel == "correlation":
        return max(4.5, 1.5 + 0.45 * len(ctx.report["covariance"]["names"]))
    if panel == "backbone":
        return 6.5
    return 4.0


def _draw(fig: Figure | SubFigure, panel: str, ctx: _Context) -> None:
    """A panel in `fig`: its title, a strip for its legend, its plots and its caption."""
    import textwrap

    fig.suptitle(ctx.title(panel), fontsize="large")
    grid = fig.add_gridspec(2, 1)
    head, body = fig.add_subfigure(grid[0]), fig.add_subfigure(grid[1])
    drawn = _DRAW[panel](body, ctx)
    strip = _legend_row(head, drawn)
    grid.set_height_ratios([strip, max(_height(panel, ctx) - strip, 1.0)])
    fig.supxlabel(textwrap.fill(drawn.caption, 140), fontsize="small")


def figure(report: Mapping[str, Any], recording: Recording | None,
           panels: str | int | Sequence[str | int] | None = None,
           ax: Axes | None = None) -> Figure:
    """One figure of the panels asked for (default: all that apply), one under another;
    with `ax`, the one panel asked for drawn in the place of that subplot."""
    Figure = _matplotlib()
    names, _ = choose(report, recording, panels)
    ctx = _Context(report, recording)
    if ax is not None:
        spec = ax.get_subplotspec()
        if len(names) != 1 or spec is None:
            raise UsageError("ax: give one panel and a subplot of a figure (from subplots or "
                             "add_subplot) to draw it in")
        parent = ax.get_figure()
        ax.remove()
        _draw(parent.add_subfigure(spec), names[0], ctx)
        return parent.get_figure(root=True)
    heights = [_height(name, ctx) for name in names]
    fig = Figure(figsize=(_WIDTH, sum(heights)), layout="constrained", dpi=_DPI)
    parts = fig.subfigures(len(names), 1, height_ratios=heights, squeeze=False)[:, 0]
    for part, name in zip(parts, names, strict=True):
        _draw(part, name, ctx)
    return fig


def pages(report: Mapping[str, Any], recording: Recording | None,
          panels: str | int | Sequence[str | int] | None = None
          ) -> tuple[list[tuple[str, Figure]], list[str]]:
    """One figure per panel (default: all that apply), and a note on each left out."""
    Figure = _matplotlib()
    names, notes = choose(report, recording, panels)
    ctx = _Context(report, recording)
    drawn = []
    for name in names:
        fig = Figure(figsize=(_WIDTH, _height(name, ctx)), layout="constrained", dpi=_DPI)
        _draw(fig, name, ctx)
        drawn.append((name, fig))
    return drawn, notes


def check_output(path: str) -> None:
    """Before any work: a figure file's extension names a format, and matplotlib is there."""
    if os.path.splitext(path)[1].lower() not in FORMATS:
        raise UsageError(f"{path!r}: a figure is written as {', '.join(FORMATS)} (told by "
                         "the extension)")
    _matplotlib()


def output_paths(path: str, names: Sequence[str]) -> list[str]:
    """Where each panel goes: all in `path` for a PDF (a page each) or a single panel,
    else STEM-K-NAME.EXT beside it."""
    stem, extension = os.path.splitext(path)
    if extension.lower() == ".pdf" or len(names) == 1:
        return [path]
    return [f"{stem}-{PANELS.index(name) + 1}-{name}{extension}" for name in names]


def panel_files(path: str, panels: str | int | Sequence[str | int] | None = None) -> list[str]:
    """The files `save` may write besides `path` itself for these panels (the six of
    `DEFAULT_PANELS` by default): STEM-K-NAME.EXT when more than one may be drawn, none for a
    PDF. A command checks them all before its work, as it checks `path`."""
    return [name for name in output_paths(path, parse_panels(panels) or DEFAULT_PANELS)
            if name != path]


def save(report: Mapping[str, Any], recording: Recording | None, path: str,
         panels: str | int | Sequence[str | int] | None = None) -> list[str]:
    """Draw the panels and write them: a PDF of a page per panel, or a PNG or SVG file per
    panel (`output_paths`), each atomically (inside `writing.all_or_nothing` all or none of
    them); returns the notes on panels left out."""
    check_output(path)
    drawn, notes = pages(report, recording, panels)
    write_pages(drawn, path)
    return notes


def write_pages(drawn: Sequence[tuple[str, Figure]], path: str) -> None:
    """Write figures named by panel: a PDF of a page each, or a PNG or SVG file each
    (`output_paths`), each atomically, with no dates in them (the same fit draws the same
    bytes)."""
    import io

    from hamid.data import writing

    extension = os.path.splitext(path)[1].lower()
    metadata = {".pdf": {"CreationDate": None}, ".svg": {"Date": None}}.get(extension)
    buffers = []
    if extension == ".pdf":
        from matplotlib.backends.backend_pdf import PdfPages

        buffer = io.BytesIO()
        with PdfPages(buffer, metadata=metadata) as pdf:
            for _, fig in drawn:
                pdf.savefig(fig)
        buffers.append(buffer.getvalue())
    else:
        for _, fig in drawn:
            buffer = io.BytesIO()
            fig.savefig(buffer, format=extension[1:], metadata=metadata)
            buffers.append(buffer.getvalue())
    for data, target in zip(buffers, output_paths(path, [n for n, _ in drawn]), strict=True):
        writing.write_bytes(data, target)
