"""The backbone report, ``hamid.backbone/1``: the fitted model's curve at chosen amplitudes
or energies with its bands, and the recording's points, as a dict, a DataFrame and text.

`Source.of_report` reads what a backbone needs from a ``hamid.fit/1`` report (plain data,
never a FitResult): the model and its dissipation, the estimates, the covariance with the
fit's interval multiplier, the energy levels and the units. `backbone_report` computes the
curve (`hamid.backbone.one_degree`, bands by `hamid.backbone.bands`) and, given the
records, the recorded points (`hamid.backbone.from_data`); `frame` and `render` show it.

Default amplitudes (neither amplitudes nor energies given): `points` amplitudes evenly
spaced from 2% of the largest recorded amplitude to it. The largest recorded amplitude is
that of the recorded points when data are given, else that of the orbit at the report's
highest energy level (a damped trajectory's level is its energy at its start), else, when
no level lies in the well, that of the orbit at 90% of the way from the well's bottom to
its rim, else 1 (model units). A normal mode whose default levels meet an internal
resonance is drawn up to the last level before it, and its entry says so (`stopped`);
levels asked for are computed as asked, or refused at the resonance.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from hamid import safe_text
from hamid.backbone.bands import Band, Uncertainty, bands, bands_along
from hamid.backbone.from_data import decay_points
from hamid.backbone.normal_modes import InternalResonanceError, ModeFitted, small_amplitude
from hamid.backbone.one_degree import Cycle, Fitted, Well
from hamid.data import column_roles
from hamid.data.records import Records
from hamid.errors import UsageError
from hamid.model.models import model_from_info

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["FORMATS", "SCHEMA", "Request", "Source", "backbone_report", "frame", "render"]

SCHEMA = "hamid.backbone/1"
FORMATS = ("table", "json", "csv")
SMALLEST = 0.02    # the default amplitudes start at this share of the largest recorded
_RIM_SHARE = 0.9   # without a level in the well: the orbit this far up to the rim
_SI = {**{unit: "m" for unit in ("m", "cm", "mm", "um", "nm")},
       **{unit: "rad" for unit in ("rad", "mrad", "deg")}}


@dataclass(frozen=True)
class Request:
    """What to compute: the levels (amplitudes of `coordinate`, or energies; neither:
    `points` default amplitudes), the mode (1-based) and the coordinate amplitudes are
    given for (default: the mode's leading coordinate)."""

    amplitudes: tuple[float, ...] | None = None
    energies: tuple[float, ...] | None = None
    mode: int = 1
    coordinate: str | None = None
    points: int = 25


@dataclass(frozen=True, eq=False)
class Source:
    """What a backbone takes from a fit report."""

    fitted: Fitted
    uncertainty: Uncertainty | None
    level: float
    levels: tuple[float, ...]          # the fitted energy levels h
    units: dict[str, str | None]       # coordinate -> SI unit of the recording, if known
    time_unit: str | None
    equilibrium: tuple[float, ...] | None = None   # the report's, at small amplitude

    @classmethod
    def of_report(cls, report: Mapping[str, Any]) -> Source:
        """The parts of a ``hamid.fit/1`` dict a backbone reads."""
        model = model_from_info(report["model"], where="the report's model")
        estimates = {p["name"]: float(p["estimate"]) for p in report["parameters"]}
        dissipation = model.dissipative(report["method"]["damping"])
        covariance = report.get("covariance")
        uncertainty = None
        if covariance is not None:
            matrix = np.array([[np.nan if x is None else x for x in row]
                               for row in covariance["matrix"]], dtype=float)
            uncertainty = Uncertainty(tuple(covariance["names"]), matrix.reshape(
                len(covariance["names"]), len(covariance["names"])), _multiplier(report))
        data = report["data"]
        small = (report.get("dissipation") or {}).get("small_amplitude")
        return cls(Fitted(model, estimates, dissipation if len(dissipation) else None),
                   uncertainty, float(report["method"]["level"]),
                   tuple(float(h["h"]) for h in report["energy_levels"]),
                   {q: _unit(data, q) for q in model.coordinates}, data.get("time_unit"),
                   equilibrium=None if not small else tuple(
                       float(small["equilibrium"][q]) for q in model.coordinates))


def _multiplier(report: Mapping[str, Any]) -> float:
    """The fit's interval half-width per standard error (its t quantile), read off a
    parameter's interval; the normal quantile at its level when none has one."""
    from scipy.stats import norm

    for p in report["parameters"]:
        if p.get("stderr") and p.get("ci_high") is not None and not p.get("fixed"):
            return (p["ci_high"] - p["estimate"]) / p["stderr"]
    return float(norm.ppf((1 + float(report["method"]["level"])) / 2))


def _unit(data: Mapping[str, Any], coordinate: str) -> str | None:
    """The SI unit of a coordinate read from a column with a unit suffix (`_mm`, `[deg]`),
    else None: the recording's own units, unknown."""
    column = data.get("columns", {}).get(coordinate)
    if column is None:
        return None
    _, unit = column_roles.column_scale(column)
    return _SI.get(unit) if unit else None


def _one_degree(source: Source, request: Request) -> Fitted:
    """The fitted model of one coordinate, the request checked against it."""
    model = source.fitted.model
    if request.mode != 1:
        raise UsageError(f"--mode {request.mode}: model {model.name!r} has 1 mode (one per "
                         "coordinate)")
    if request.coordinate not in (None, model.coordinates[0]):
        raise UsageError(f"--coordinate {request.coordinate!r}: not a coordinate of model "
                         f"{model.name!r} ({model.coordinates[0]})")
    return source.fitted


def _largest(fitted: Fitted, well: Well, source: Source,
             recorded: Sequence[float]) -> float:
    """The largest recorded amplitude (the module's rule)."""
    if len(recorded):
        return float(max(recorded))
    inside = [h for h in source.levels if h > well.floor and
              (well.rim is None or h < well.rim.energy)]
    if inside:
        return well.orbit(max(inside)).amplitude
    if well.rim is not None:
        return well.orbit(well.floor + _RIM_SHARE * (well.rim.energy - well.floor)).amplitude
    return 1.0


def backbone_report(source: Source, request: Request, *, records: Records | None = None,
                    names: Sequence[str] = ()) -> dict[str, Any]:
    """The ``hamid.backbone/1`` dict (docs/output.md): the curve at the requested levels,
    bands at the fit's level, and with `records` (read from the files `names`) the
    recorded points."""
    if len(source.fitted.model.coordinates) > 1:
        return _normal_modes_report(source, request, records=records, names=names)
    fitted = _one_degree(source, request)
    coordinate = fitted.model.coordinates[0]
    if records is not None:
        q = records.X[:, 0]
        fitted = replace(fitted, near=float(np.median(q)),
                         scale=float(max(np.ptp(q) / 2, np.finfo(float).tiny)))
    elif source.equilibrium is not None:
        fitted = replace(fitted, near=source.equilibrium[0])
    well = fitted.well()
    data = [] if records is None else decay_points(records, 0, well.bottom)
    if request.energies is not None:
        orbits = [well.orbit(e) for e in request.energies]
    else:
        amplitudes = request.amplitudes
        if amplitudes is None:
            top = _largest(fitted, well, source,
                           [a for d in data for a in d.amplitude.tolist()])
            amplitudes = tuple(np.linspace(SMALLEST * top, top, request.points).tolist())
        orbits = [well.orbit_at(a) for a in amplitudes]
    points = []
    for orbit in orbits:
        cycle = fitted.cycle(well, orbit)
        band = (bands(replace(fitted, near=well.bottom), orbit.amplitude, source.uncertainty,
                      centre=cycle) if source.uncertainty is not None else None)
        points.append({**_point(cycle, {coordinate: orbit.amplitude}, band),
                       "energy": orbit.energy})
    return _document(source, fitted.model.name, {
        "equilibrium": {coordinate: well.bottom},
        "rim": None if well.rim is None else {"energy": well.rim.energy,
                                              coordinate: well.rim.position},
        "modes": [{"mode": 1, "coordinate": coordinate, "points": points}],
        **_data(source, data, coordinate, names)})


def _point(cycle: Cycle, amplitude: dict[str, float], band: Band | None) -> dict[str, Any]:
    """One point of a curve: its level, frequency and damping ratio with their bands."""
    f_band = band.frequency if band and band.frequency else (None, None)
    z_band = band.damping_ratio if band and band.damping_ratio else (None, None)
    return {"energy": cycle.excess, "amplitude": amplitude, "frequency_hz": cycle.frequency,
            "frequency_hz_low": f_band[0], "frequency_hz_high": f_band[1],
            "damping_ratio": cycle.damping_ratio, "damping_ratio_low": z_band[0],
            "damping_ratio_high": z_band[1]}


def _data(source: Source, data: Sequence[Any], coordinate: str,
          names: Sequence[str]) -> dict[str, Any]:
    """The recorded points, trajectory by trajectory (`data`), and a note on them (`notes`):
    a driven recording's are left out, its periods being the drive's, not the free
    orbits' (they still set the default amplitudes)."""
    if data and source.fitted.model.inputs:
        return {"data": [], "notes": ["the recording is driven: its periods are the "
                                      "drive's, not the free orbits', and are left out"]}
    return {"notes": [], "data": [
        {"source": ", ".join(names) or None, "trajectory": d.trajectory,
         "coordinate": coordinate,
         "points": [{"t": t, "amplitude": a, "frequency_hz": f}
                    for t, a, f in zip(d.t.tolist(), d.amplitude.tolist(),
                                       d.frequency.tolist(), strict=True)]}
        for d in data]}


def _document(source: Source, model: str, curve: Mapping[str, Any]) -> dict[str, Any]:
    """The ``hamid.backbone/1`` dict around a curve (equilibrium, rim, modes, data)."""
    from hamid import __version__

    return _plain({
        "schema": SCHEMA, "hamid_version": __version__, "model": model, "level": source.level,
        "bands": None if source.uncertainty is None else
        "delta method: central differences of each value in each free parameter at fixed "
        "amplitude, with the fit's covariance, times the fit's interval multiplier "
        f"{source.uncertainty.multiplier:.4g}",
        "units": {"amplitude": source.units, "time": source.time_unit}, **curve})


def _normal_modes_report(source: Source, request: Request, *, records: Records | None,
                         names: Sequence[str]) -> dict[str, Any]:
    """The backbone of a model of several coordinates: a nonlinear normal mode continued
    from its linear mode (`hamid.backbone.normal_modes`), led by `request.coordinate`
    (default: the mode's largest). Default levels: `points` energies evenly spaced from 2%
    of the highest fitted level above the equilibrium's to it (with data, amplitudes of
    the leading coordinate up to the largest recorded one)."""
    model = source.fitted.model
    if request.coordinate is not None and request.coordinate not in model.coordinates:
        raise UsageError(f"--coordinate {request.coordinate!r}: not a coordinate of model "
                         f"{model.name!r} ({', '.join(model.coordinates)})")
    lead = (None if request.coordinate is None
            else model.coordinates.index(request.coordinate))
    near = (source.equilibrium if records is None else
            tuple(np.median(records.X[:, :len(model.coordinates)], axis=0).tolist()))
    mode = ModeFitted(model, source.fitted.estimates, source.fitted.dissipation,
                      request.mode, lead, near)
    limit = small_amplitude(model, source.fitted.estimates, near=near)
    if not 1 <= request.mode <= len(limit.modes):
        raise UsageError(f"--mode {request.mode}: model {model.name!r} has modes 1 to "
                         f"{len(limit.modes)}")
    shape = limit.modes[request.mode - 1].shape
    lead = int(np.argmax(np.abs(shape))) if lead is None else lead
    coordinate = model.coordinates[lead]
    equilibrium = limit.equilibrium
    data = ([] if records is None
            else decay_points(records, lead, float(equilibrium[lead])))
    amplitudes, energies = request.amplitudes, request.energies
    default = amplitudes is None and energies is None
    if default:
        recorded = [a for d in data for a in d.amplitude.tolist()]
        if recorded:
            amplitudes = tuple(np.linspace(SMALLEST * max(recorded), max(recorded),
                                           request.points).tolist())
        else:
            top = max(h for h in source.levels) - _equilibrium_energy(source, equilibrium)
            if not top > 0:
                raise UsageError("backbone: no fitted level lies above the equilibrium; "
                                 "give --amplitudes or --energies")
            energies = tuple(np.linspace(SMALLEST * top, top, request.points).tolist())
    mode = replace(mode, lead=lead)
    stopped = None
    try:
        found = mode.orbits(amplitudes=amplitudes, energies=energies)
    except InternalResonanceError as error:
        if not default or len(error.orbits) < 2:
            raise
        # the default levels end at the last before the resonance, and the report says why
        stopped = str(error)
        found = [(mode.cycle(orbit), orbit) for orbit in error.orbits]
    orbits = [orbit for _, orbit in found]   # the bands at their amplitudes of the lead
    found_bands = ([None] * len(found) if source.uncertainty is None else bands_along(
        mode, [cycle for cycle, _ in found], source.uncertainty,
        lambda nudged: nudged.corrected(orbits)))
    points = [_point(cycle, dict(zip(model.coordinates, orbit.amplitudes.tolist(),
                                     strict=True)), band)
              for (cycle, orbit), band in zip(found, found_bands, strict=True)]
    return _document(source, model.name, {
        "equilibrium": dict(zip(model.coordinates, equilibrium.tolist(), strict=True)),
        "rim": None,
        "modes": [{"mode": request.mode, "coordinate": coordinate, "points": points,
                   "stopped": stopped}],
        **_data(source, data, coordinate, names)})


def _equilibrium_energy(source: Source, equilibrium: npt.NDArray[np.float64]) -> float:
    """The fitted energy at rest at the equilibrium."""
    model = source.fitted.model
    theta = [source.fitted.estimates[p] for p in model.parameters]
    state = np.concatenate([equilibrium, np.zeros(len(model.velocities))])[None]
    return float(model.total_energy(state, theta)[0])


def _plain(value: Any) -> Any:
    """Numpy scalars as Python's, non-finite numbers as None (JSON's null)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


COLUMNS = ("frequency_hz", "frequency_hz_low", "frequency_hz_high", "damping_ratio",
           "damping_ratio_low", "damping_ratio_high")


def frame(document: Mapping[str, Any]) -> pd.DataFrame:
    """The curve as a DataFrame, a row per point: mode, energy, amplitude_<q>, then
    `COLUMNS` (NaN where unknown)."""
    import pandas as pd

    rows = [{"mode": mode["mode"], "energy": p["energy"],
             **{f"amplitude_{q}": a for q, a in p["amplitude"].items()},
             **{key: p[key] for key in COLUMNS}}
            for mode in document["modes"] for p in mode["points"]]
    table = pd.DataFrame(rows)
    numbers = [c for c in table.columns if c != "mode"]
    table[numbers] = table[numbers].astype(float)
    return table


def _number(value: float | None) -> str:
    return "—" if value is None else f"{value:.6g}"


def render(document: Mapping[str, Any], fmt: str) -> str:
    """The report as ``json``, ``csv`` (the curve's rows, `frame`) or ``table`` (text for a
    terminal)."""
    if fmt == "json":
        return json.dumps(document, indent=2, allow_nan=False, ensure_ascii=True) + "\n"
    if fmt == "csv":
        return frame(document).to_csv(index=False, lineterminator="\n")
    if fmt != "table":
        raise UsageError(f"unknown backbone format {fmt!r} (choose from "
                         f"{', '.join(FORMATS)})")
    out = io.StringIO()
    units = document["units"]["amplitude"]
    out.write(safe_text.printable(
        f"hamid backbone — model {document['model']}, bands at "
        f"{100 * document['level']:g}%" + ("" if document["bands"] else " (no covariance)"))
        + "\n")
    for mode in document["modes"]:
        q = mode["coordinate"]
        names = ["energy", f"amplitude {q}", "f (Hz)", "f low", "f high", "zeta", "zeta low",
                 "zeta high"]
        rows = [[_number(c) for c in (p["energy"], p["amplitude"][q],
                                      *(p[key] for key in COLUMNS))] for p in mode["points"]]
        widths = [max(len(cell) for cell in column) for column in zip(names, *rows,
                                                                      strict=True)]
        out.write(safe_text.printable(
            f"mode {mode['mode']} (amplitude of {q} in {units.get(q) or 'model units'})")
            + "\n")
        if mode.get("stopped"):
            out.write(safe_text.printable(f"the default levels end short of {mode['stopped']}")
                      + "\n")
        for cells in [names, *rows]:
            out.write(safe_text.printable("  ".join(
                f"{cell:>{width}}" for cell, width in zip(cells, widths, strict=True))) + "\n")
    for d in document["data"]:
        out.write(safe_text.printable(
            f"recorded: trajectory {d['trajectory']}, {len(d['points'])} periods") + "\n")
    for note in document["notes"]:
        out.write(safe_text.printable(f"note: {note}") + "\n")
    return out.getvalue()

