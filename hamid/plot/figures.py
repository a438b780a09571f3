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
6. ``correlation``: the correlation matrix of the estimates.

Panels 1-4 need the records (`hamid.data.records.Recording`), panel 4 the trajectory
refinement; 5 and 6 need only the report. Figures are made without pyplot, so no window
ever opens and no backend is chosen: headless wherever it runs.
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
from hamid.plot import fitted

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure, SubFigure

__all__ = ["FORMATS", "PANELS", "check_output", "choose", "figure", "output_paths", "pages",
           "panel_files", "parse_panels", "save"]

PANELS = ("energy", "residuals", "phase", "motion", "parameters", "correlation")
FORMATS = (".png", ".svg", ".pdf")
_TITLES = {"energy": "Energy over time", "residuals": "Energy residuals",
           "phase": "Phase portraits", "motion": "Recorded and fitted motion",
           "parameters": "Parameters", "correlation": "Correlation of the estimates"}
# Okabe & Ito's colour-blind-safe palette (yellow left out: it vanishes on white).
OKABE_ITO = ("#0072B2", "#E69F00", "#009E73", "#D55E00", "#CC79A7", "#56B4E9", "#000000")
_RESIDUAL_MAP = "berlin"     # diverging, dark at zero: visible on white, colour-blind safe
_CORRELATION_MAP = "RdBu_r"  # ColorBrewer's diverging map, colour-blind safe
MAX_SHOWN = 6                # trajectories drawn one by one; later ones are left out
MAX_POINTS = 20_000          # samples drawn per series; longer ones are thinned evenly
# Parameters a panel shows: a row each in panel 5 (302 rows took 103 s and 461 MB), a row
# and a column of panel 6's matrix.
MAX_PARAMETERS = {"parameters": 40, "correlation": 200}
_LONGEST_NAME = 40           # characters of a name from the report shown in a figure
_WIDTH = 10.0                # inches
_DPI = 120


def _matplotlib() -> Any:
    """matplotlib's Figure class, or a one-line error naming the extra to install."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise HamidError("drawing figures needs matplotlib: pip install 'hamid[plot]'") \
            from exc
    return Figure


def parse_panels(panels: str | int | Sequence[str | int] | None) -> tuple[str, ...] | None:
    """Panel names from numbers (1-6) or names, a comma list or a sequence; None for all
    that apply."""
    if panels is None:
        return None
    items = panels.split(",") if isinstance(panels, str) else \
        [panels] if isinstance(panels, int) else list(panels)
    names = []
    for item in items:
        text = str(item).strip().lower()
        name = PANELS[int(text) - 1] if text in {str(k) for k in range(1, 7)} else text
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
        name, estimate, low, high = _plain(p["name"]), p["estimate"], p["ci_low"], p["ci_high"]
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


def _plain(name: Any) -> str:
    """A name from the report as plain text in a figure: cut to `_LONGEST_NAME`
    characters, its dollar signs escaped (mathtext parsed an edited report's "$x^$", and
    3,000 nested braces overflowed its parser's recursion)."""
    text = str(name)
    if len(text) > _LONGEST_NAME:
        text = text[:_LONGEST_NAME - 1] + "…"
    return text.replace("$", r"\$")


def choose(report: Mapping[str, Any], recording: Recording | None,
           panels: str | int | Sequence[str | int] | None = None
           ) -> tuple[tuple[str, ...], list[str]]:
    """The panels to draw, and a note on those left out (one per reason): by default all
    that apply; a panel asked for that cannot be drawn is an error."""
    asked = parse_panels(panels)
    drawn, left_out = [], {}
    for k, panel in enumerate(PANELS, 1):
        if asked is not None and panel not in asked:
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

    @property
    def labels(self) -> list[str]:
        return [_plain(level["trajectory"]) for level in self.report["energy_levels"]]

    @property
    def shown(self) -> range:
        """The trajectories drawn one by one."""
        return range(min(len(self.labels), MAX_SHOWN))

    @property
    def shown_note(self) -> str:
        """Said in a caption when trajectories were left out."""
        n = len(self.labels)
        return f"; the first {MAX_SHOWN} of {n} trajectories shown" if n > MAX_SHOWN else ""

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

    def label(self, name: str) -> str:
        """A model variable's axis label, with its SI unit when its column named one."""
        column = self.report["data"]["columns"].get(name, name)
        unit = column_roles.column_scale(column)[1]
        if unit is None:
            return name
        base = "rad" if unit.removesuffix("_s") in ("rad", "mrad", "deg") else "m"
        return f"{name} [{base}/s]" if unit.endswith("_s") else f"{name} [{base}]"

    def title(self, panel: str) -> str:
        """The panel's title: what it shows, the files and the method."""
        report = self.report
        sources = [_plain(os.path.basename(s).strip("<>")) for s in report["data"]["sources"]]
        files = ", ".join(sources[:2]) + (f" and {len(sources) - 2} more"
                                          if len(sources) > 2 else "")
        method = report["method"]
        refined = (method.get("refinement") or {}).get("applied")
        return (f"{PANELS.index(panel) + 1}. {_TITLES[panel]}: {files or 'data'} — "
                f"{_plain(report['model']['name'])}, method {method['kind']}"
                f"{' + trajectory refinement' if refined else ''}")


def _ticks(n: int) -> Any:
    """A locator of at most n ticks at round numbers."""
    from matplotlib.ticker import MaxNLocator

    return MaxNLocator(n, steps=[1, 2, 2.5, 5, 10])


def _middle(fig: Figure | SubFigure) -> Any:
    """The middle of three columns of a panel: room for a square plot and its colour bar."""
    return fig.add_gridspec(1, 3, width_ratios=(1, 1.6, 1))[0, 1]


def _thin(n: int) -> slice:
    """Every k-th of n samples, so that at most MAX_POINTS are drawn."""
    return slice(None, None, max(1, -(-n // MAX_POINTS)))


def _colour(j: int) -> str:
    return OKABE_ITO[j % len(OKABE_ITO)]


def _legend_above(ax: Axes, columns: int) -> None:
    """The axes' legend in a row above it, outside the data."""
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncols=columns, frameon=False,
              fontsize="small")


def _draw_energy(fig: Figure | SubFigure, ctx: _Context) -> str:
    e = ctx.energies
    axes = fig.subplots(len(ctx.shown), 1, sharex=True, squeeze=False)[:, 0]
    for ax, j in zip(axes, ctx.shown, strict=True):
        rows = ctx.rows(j)
        step = _thin(rows.stop - rows.start)
        t, level, band = e.time[rows][step], e.level[rows][step], 2 * e.noise[rows][step]
        ax.fill_between(t, level - band, level + band, color=OKABE_ITO[5], alpha=0.35,
                        linewidth=0, label="±2σ of the measurement noise")
        ax.plot(t, e.energy[rows][step], color=OKABE_ITO[0], linewidth=0.9,
                label="E(q, v; θ) at the fitted θ")
        ax.plot(t, level, color="black", linestyle="--", linewidth=1.2,
                label="h − dissipated work" if ctx.damped else
                "mean energy (weak rows fit no level)" if ctx.report["method"]["kind"] == "weak"
                else "fitted level h")
        ax.set_ylabel(f"E, trajectory {ctx.labels[j]}")
    axes[-1].set_xlabel(ctx.time_label)
    _legend_above(axes[0], 3)
    return ("the band is twice the standard deviation the measurement noise puts into E at "
            f"each sample{ctx.shown_note}")


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
    for j in ctx.shown:
        rows = ctx.rows(j)
        step = _thin(rows.stop - rows.start)
        series.plot(e.time[rows][step], e.residual[rows][step], color=_colour(j),
                    linewidth=0.7, label=f"trajectory {ctx.labels[j]}")
    series.axhline(0.0, color="grey", linewidth=0.8)
    series.set(xlabel=ctx.time_label, ylabel="energy residual r")
    _legend_above(series, min(3, len(ctx.shown)))
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
                   linewidth=1.5, label="standard normal")
    spread = float(np.std(z)) if z.size else 1.0
    if not 0.5 < spread < 2.0:   # misfit beyond the noise: the residuals' own scale too
        histogram.plot(x, np.exp(-(x / spread)**2 / 2) / (spread * np.sqrt(2 * np.pi)),
                       color=OKABE_ITO[5], linewidth=1.2, linestyle="--",
                       label=f"normal, sd {spread:.3g}")
        # scaled to the residuals: the standard normal's peak runs off the top
        histogram.set_ylim(0.0, max(heights.max(initial=0.0),
                                    1 / (spread * np.sqrt(2 * np.pi))))
    histogram.set(xlabel="r / σ", ylabel="density", title="histogram")
    histogram.legend(fontsize="small", loc="upper left")
    histogram.set_ylim(top=1.35 * histogram.get_ylim()[1])   # room for the legend
    bounds = ctx.recording.records.bounds()  # type: ignore[union-attr]
    lags = max(1, min(40, min(stop - start for start, stop in bounds) // 4))
    # lag 0 is 1 by definition: from lag 1 on, the scale shows what matters
    correlation.bar(np.arange(1, lags + 1), _autocorrelation(r, bounds, lags)[1:],
                    color=OKABE_ITO[2], width=0.8)
    limit = 1.96 / np.sqrt(len(r))
    correlation.axhspan(-limit, limit, color="grey", alpha=0.25, linewidth=0)
    correlation.axhline(0.0, color="grey", linewidth=0.8)
    correlation.set(xlabel="lag [samples]", ylabel="autocorrelation", title="autocorrelation")
    series.ticklabel_format(axis="y", style="sci", scilimits=(-2, 3))
    histogram.xaxis.set_major_locator(_ticks(3))
    return (f"r = E(q, v; θ) − h{' + the dissipated work' if ctx.damped else ''}; σ: the "
            "standard deviation the measurement noise puts into E (the energy panel's band); "
            "autocorrelation over pairs within trajectories, grey: the 95% band of white noise"
            f"{ctx.shown_note}")


def _draw_phase(fig: Figure | SubFigure, ctx: _Context) -> str:
    from matplotlib.colors import Normalize

    model, records = ctx.recording.model, ctx.recording.records  # type: ignore[union-attr]
    e = ctx.energies
    N = len(model.coordinates)
    columns = min(N, 3)
    if N == 1:   # alone it would stretch across the page: the middle, its colour bar beside
        axes = np.array([fig.add_subplot(_middle(fig))])
    else:
        axes = fig.subplots(-(-N // columns), columns, squeeze=False).ravel()
    shown = np.concatenate([np.arange(ctx.rows(j).start, ctx.rows(j).stop) for j in ctx.shown])
    scale = float(np.quantile(np.abs(e.residual[shown]), 0.99)) or 1.0
    norm = Normalize(-scale, scale)
    h = [level["h"] for level in ctx.report["energy_levels"]]
    points = None
    for i, ax in enumerate(axes[:N]):
        q, v = records.X[shown, i], records.X[shown, N + i]
        margin_q, margin_v = 0.12 * np.ptp(q) or 1.0, 0.12 * np.ptp(v) or 1.0
        grid_q = np.linspace(q.min() - margin_q, q.max() + margin_q, 100)
        grid_v = np.linspace(v.min() - margin_v, v.max() + margin_v, 100)
        for j in ctx.shown:
            rows = ctx.rows(j)
            step = _thin(rows.stop - rows.start)
            points = ax.scatter(records.X[rows, i][step], records.X[rows, N + i][step],
                                c=e.residual[rows][step], cmap=_RESIDUAL_MAP, norm=norm,
                                s=4, linewidths=0, zorder=2)
            lowest = fitted.lowest_energy(ctx.report, ctx.recording,  # type: ignore[arg-type]
                                          i, j, grid_q, grid_v)
            # solid whatever the sign: matplotlib dashes the contours of negative levels
            ax.contour(grid_q, grid_v, lowest, levels=[h[j]], colors=[_colour(j)],
                       linewidths=1.0, linestyles="solid", zorder=1)
            ax.plot([], [], color=_colour(j), label=f"E = h, trajectory {ctx.labels[j]}")
        ax.set(xlabel=ctx.label(model.coordinates[i]), ylabel=ctx.label(model.velocities[i]))
    for ax in axes[N:]:
        ax.set_axis_off()
    bar = fig.colorbar(points, ax=list(axes[:N]), label="energy residual r", shrink=0.9)
    bar.formatter.set_powerlimits((-2, 3))
    _legend_above(axes[0], min(3, len(ctx.shown)))
    return ("points: the samples, coloured by their energy residual; lines: "
            + ("E = h of each trajectory" if N == 1 else
               "where E reaches each trajectory's level h, the other coordinates as recorded "
               "and their velocities at rest (the bound of the motion at that level)")
            + ("; with damping, h is the energy at the start" if ctx.damped else "")
            + ctx.shown_note)


def _draw_motion(fig: Figure | SubFigure, ctx: _Context) -> str:
    model = ctx.recording.model  # type: ignore[union-attr]
    axes = fig.subplots(2 * len(ctx.shown), 1, height_ratios=[3, 1] * len(ctx.shown),
                        squeeze=False)[:, 0]
    for k, j in enumerate(ctx.shown):
        motion, misfit = axes[2 * k], axes[2 * k + 1]
        segment = fitted.segment_motion(ctx.report, ctx.recording,  # type: ignore[arg-type]
                                        j)
        step = _thin(len(segment.t))
        t = segment.t[step]
        for i, name in enumerate(model.coordinates):
            recorded, integrated = segment.recorded[step, i], segment.model[step, i]
            motion.plot(t, recorded, linestyle="none", marker="o", markersize=2, alpha=0.45,
                        color=_colour(i), label=f"{name} recorded", zorder=2)
            motion.plot(t, integrated, color=_colour(i), linewidth=1.4,
                        label=f"{name} fitted model", zorder=3)
            misfit.plot(t, recorded - integrated, color=_colour(i), linewidth=0.7)
        motion.set_ylabel(f"trajectory {ctx.labels[j]}")
        misfit.set_ylabel("recorded\n− model", fontsize="small")
        misfit.axhline(0.0, color="grey", linewidth=0.8)
        motion.sharex(misfit)
        motion.tick_params(labelbottom=False)
        misfit.ticklabel_format(axis="y", style="sci", scilimits=(-2, 3))
    axes[-1].set_xlabel(ctx.time_label)
    _legend_above(axes[0], 2 * len(model.coordinates))
    return ("the first refinement segment of each trajectory, the fitted model integrated "
            f"from its best-fitting initial state{ctx.shown_note}")


def _draw_parameters(fig: Figure | SubFigure, ctx: _Context) -> str:
    parameters = ctx.report["parameters"]
    level = ctx.report["method"]["level"]
    axes = fig.subplots(len(parameters), 1, squeeze=False)[:, 0]
    for ax, p in zip(axes, parameters, strict=True):
        estimate, low, high, truth = p["estimate"], p["ci_low"], p["ci_high"], p["truth"]
        text = f"{_plain(p['name'])} = {estimate:.6g}"
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
        ax.set_title(text, fontsize="medium", loc="left")
        if reach < 1e-4 * abs(estimate):
            # ticks as distances from a round number near the estimate
            offset = float(np.round(estimate, -int(np.floor(np.log10(reach))) - 1))
            ax.ticklabel_format(axis="x", useOffset=offset, style="sci", scilimits=(-3, 4))
        else:
            ax.ticklabel_format(axis="x", useOffset=False, style="plain")
        ax.xaxis.set_major_locator(_ticks(7))
    axes[-1].set_xlabel("estimate")
    truth = ", dashed: the truth" if any(p["truth"] is not None for p in parameters) else ""
    return f"bars: {100 * level:g}% confidence intervals{truth}; each row on its own scale"


def _draw_correlation(fig: Figure | SubFigure, ctx: _Context) -> str:
    covariance = ctx.report["covariance"]
    names = [_plain(name) for name in covariance["names"]]
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
    return "the correlations of the free parameters' estimates, from their covariance"


_DRAW: dict[str, Callable[[Any, _Context], str]] = {
    "energy": _draw_energy, "residuals": _draw_residuals, "phase": _draw_phase,
    "motion": _draw_motion, "parameters": _draw_parameters, "correlation": _draw_correlation,
}


def _height(panel: str, ctx: _Context) -> float:
    """The panel's height in inches, for its number of rows."""
    if panel == "energy":
        return 0.9 + 2.0 * len(ctx.shown)
    if panel == "motion":
        return 0.9 + 2.8 * len(ctx.shown)
    if panel == "phase":
        n = len(ctx.recording.model.coordinates)  # type: ignore[union-attr]
        return 0.8 + 3.6 * -(-n // 3)
    if panel == "parameters":
        return 1.0 + 0.85 * len(ctx.report["parameters"])
    if panel == "correlation":
        return max(4.5, 1.5 + 0.45 * len(ctx.report["covariance"]["names"]))
    return 4.0


def _draw(fig: Figure | SubFigure, panel: str, ctx: _Context) -> None:
    import textwrap

    fig.suptitle(ctx.title(panel), fontsize="large")
    caption = _DRAW[panel](fig, ctx)
    fig.supxlabel(textwrap.fill(caption, 140), fontsize="small")


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
    """The files `save` may write besides `path` itself for these panels (all six by
    default): STEM-K-NAME.EXT when more than one may be drawn, none for a PDF. A command
    checks them all before its work, as it checks `path`."""
    return [name for name in output_paths(path, parse_panels(panels) or PANELS)
            if name != path]


def save(report: Mapping[str, Any], recording: Recording | None, path: str,
         panels: str | int | Sequence[str | int] | None = None) -> list[str]:
    """Draw the panels and write them: a PDF of a page per panel, or a PNG or SVG file per
    panel (`output_paths`), each atomically (inside `writing.all_or_nothing` all or none of
    them); returns the notes on panels left out."""
    import io

    from hamid.data import writing

    check_output(path)
    drawn, notes = pages(report, recording, panels)
    extension = os.path.splitext(path)[1].lower()
    # no dates in the files: the same fit draws the same bytes
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
    return notes
