"""`hamid select`: which terms of a library are in the energy, and the chosen model refitted.

`choose` runs the search: the records read once, the library's rows built and weighted
once (`hamid.linear.estimate.fit_rows`, every term free), collinear terms set aside, then the
subsets scored from those rows (`hamid.selection.best_subsets`). `select` refits the chosen model
on the one path of `hamid.fit` (joint rows, then the trajectory refinement) and returns a
`Selection`, whose `to_dict()` is the JSON report ``hamid.select/1`` (docs/output.md).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hamid import __version__
from hamid.data import loading
from hamid.errors import DataError, FitError, UsageError
from hamid.linear import estimate, plan, solve
from hamid.linear.unknowns import Unknowns
from hamid.model.dissipation import Dissipation
from hamid.model.models import Model, parse_poly_name, poly_model_over
from hamid.options import OPTION_GROUPS, FitOptions, check_replicates
from hamid.result.fit_result import FitResult, plain_data
from hamid.selection import best_subsets
from hamid.selection.library import Library

__all__ = ["SCHEMA", "Choice", "SelectOptions", "Selection", "choose", "select"]

SCHEMA = "hamid.select/1"
# The keywords of `hamid.fit` that `select` takes and passes on: how the records are read,
# velocities included (`options.OPTION_GROUPS`).
READING_KEYWORDS = OPTION_GROUPS["reading"] + OPTION_GROUPS["velocities"]
DEFAULT_DEGREE = 4
MIN_REPLICATES = 10
RULES = {
    "bic": "the fewest terms within 2 of the lowest BIC, the lowest of them",
    "aic": "the fewest terms within 2 of the lowest AIC, the lowest of them",
    "cv": "the fewest terms within one standard error of the lowest cross-validated error "
          "(the one-standard-error rule), the lowest of them",
}
CONDITIONAL = ("conditional on the chosen terms: they leave out the uncertainty of the "
               "choice itself")


@dataclass(frozen=True)
class SelectOptions:
    """What to choose from and how: the library (a model whose every parameter is a
    candidate term: ``poly:N:D``, a model file or a Model; None for ``poly:N:4`` over the
    data's coordinates), the terms always kept, the criterion, and the bootstrap
    replicates (0: none) and seed of the inclusion probabilities."""

    library: str | os.PathLike[str] | Model | None = None
    keep: tuple[str, ...] = ()
    criterion: str = "bic"
    stability: int = 0
    seed: int | None = 0

    def __post_init__(self) -> None:
        if self.criterion not in best_subsets.CRITERIA:
            raise UsageError(f"criterion must be one of {', '.join(best_subsets.CRITERIA)}, "
                             f"found {self.criterion!r}")
        if self.stability and self.stability < MIN_REPLICATES:
            raise UsageError(f"--stability needs at least {MIN_REPLICATES} replicates, "
                             f"found {self.stability}")
        check_replicates("--stability", self.stability)
        if self.stability and self.criterion == "cv":
            raise UsageError("--stability cannot be combined with --criterion cv (copies of "
                             "a resampled window would sit in training and test folds); use "
                             "bic or aic")


@dataclass(frozen=True, kw_only=True)
class Choice:
    """The outcome of the search, in the library's term positions.

    chosen, kept : the chosen terms, and those kept in whatever the data say.
    collinear : each term set aside, with the simpler terms it cannot be told apart from.
    ranking : the best subsets (columns of the search's design, see `columns`).
    columns : the library term of each column of the design (None: a damping coefficient).
    inclusion : term -> share of bootstrap replicates choosing it, or None.
    kind, n_rows, n_effective : the rows scored (energy, weak or joint), their number and
        effective number.
    """

    library: Library
    options: SelectOptions
    chosen: tuple[int, ...]
    kept: tuple[int, ...]
    collinear: tuple[tuple[int, tuple[int, ...]], ...]
    ranking: best_subsets.Ranking
    columns: tuple[int | None, ...]
    inclusion: dict[int, float] | None
    kind: str
    n_rows: int
    n_effective: float

    def terms(self, columns: Sequence[int]) -> list[str]:
        """The expressions of the library terms among design columns."""
        return self.library.texts([self.columns[c] for c in columns
                                   if self.columns[c] is not None])

    @property
    def warnings(self) -> list[str]:
        """One line per group of terms set aside as collinear with the same simpler ones."""
        groups: dict[tuple[int, ...], list[int]] = {}
        for term, partners in self.collinear:
            groups.setdefault(partners, []).append(term)
        lines = []
        for partners, terms in groups.items():
            dropped = " and ".join(", ".join(self.library.texts(terms)).rsplit(", ", 1))
            simpler = ", ".join(self.library.texts(partners))
            lines.append(f"{dropped} cannot be told apart from {simpler} on these data "
                         f"(collinear): kept the simpler {simpler}, left out {dropped}")
        return lines


@dataclass(frozen=True)
class Selection:
    """A selection and the refit of the chosen model; `to_dict()` is ``hamid.select/1``."""

    choice: Choice
    model: Model
    fit: FitResult

    @property
    def chosen(self) -> list[str]:
        """The chosen terms, as expressions in the model's syntax."""
        return self.choice.library.texts(self.choice.chosen)

    def model_file(self) -> str:
        """The chosen model as a TOML model file that ``hamid fit --model`` reads."""
        c = self.choice
        notes = [f"chosen by hamid select {__version__} from the library {c.library.name} "
                 f"({c.options.criterion}): {', '.join(self.chosen)}"]
        damping = self.fit.method.get("damping") or []
        if damping:
            notes.append(f"fitted with --damping {','.join(damping)}")
        return c.library.toml(c.chosen, self.model.name, notes)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready data (docs/output.md, "hamid select")."""
        c = self.choice
        best = c.ranking.candidates[0].score
        return plain_data({
            "schema": SCHEMA,
            "hamid_version": __version__,
            "library": {"name": c.library.name,
                        "terms": [t.text for t in c.library.terms],
                        "parameters": [t.parameter for t in c.library.terms]},
            "criterion": c.options.criterion,
            "search": "exhaustive" if c.ranking.exhaustive else "stepwise",
            "rule": RULES[c.options.criterion],
            "rows": {"kind": c.kind, "n_rows": c.n_rows, "effective_rows": c.n_effective,
                     "subsets_scored": c.ranking.evaluated},
            "kept": c.library.texts(c.kept),
            "collinear": [{"term": c.library.terms[t].text,
                           "with": c.library.texts(partners)} for t, partners in c.collinear],
            "chosen": self.chosen,
            "inclusion": None if c.inclusion is None else {
                c.library.terms[t].text: p for t, p in c.inclusion.items()},
            "stability": None if c.inclusion is None else {
                "replicates": c.options.stability, "seed": c.options.seed},
            "candidates": [{"terms": c.terms(m.columns), "criterion": m.score,
                            "delta": m.score - best, "residual_variance": m.variance,
                            "chosen": m == c.ranking.chosen}
                           for m in c.ranking.candidates],
            "intervals": CONDITIONAL,
            "warnings": c.warnings,
            "fit": self.fit.to_dict(),
        })


def _library_source(data: Any, library: str | os.PathLike[str] | Model | None,
                    options: FitOptions) -> loading.Loaded:
    """The records with the library as their model: ``poly:N:D`` (or None) over the
    coordinates of the data's own model or columns, else the model given."""
    if isinstance(library, Model) or (library is not None
                                      and not os.fspath(library).startswith("poly:")):
        return loading.load(data, library, options)
    name = None if library is None else os.fspath(library)
    if options.columns:
        if name is None:
            raise UsageError("--columns needs --library (poly:N:D names the coordinates "
                             "q1..qN and velocities v1..vN, or a model file names them)")
        return loading.load(data, name, options)
    try:
        source = loading.load(data, None, options)
    except DataError as exc:
        if "no coordinate with a velocity column" not in str(exc):
            raise
        # the reader's advice names fit's --model; select takes the library instead
        raise DataError(f"{str(exc).split(';')[0]}; give --library MODEL.toml, or --library "
                        "poly:N:D with --columns q1=COL,v1=COL,...") from exc
    found = source.model
    degree = DEFAULT_DEGREE
    if name is not None:
        n, degree = parse_poly_name(name)
        if n != len(found.coordinates):
            raise UsageError(f"--library {name}: {n} coordinate{'s' if n > 1 else ''}, but "
                             f"the data have {len(found.coordinates)} "
                             f"({', '.join(found.coordinates)})")
    return dataclasses.replace(source, truth={}, model=poly_model_over(
        found.coordinates, found.velocities, degree))


def _collinear(source: loading.Loaded, library: Library, kept: Sequence[int],
               forces: Dissipation, options: FitOptions
               ) -> tuple[list[tuple[int, tuple[int, ...]]], plan.FitPlan]:
    """The terms the rows cannot tell apart from simpler ones, each with those ones, and
    the plan of the rows; an error when kept terms or damping coefficients are among them.

    Found on the rows themselves, each block scaled to unit size, before any fit: the
    rows of the whole library could not be solved with them in.
    """
    m, n_terms = source.model, len(library.terms)
    fit_plan = plan.decide(options, m, source.scales())
    raw, fit_plan = estimate.rows_of(source, Unknowns.of(m, forces.names, {}),
                                     forces, fit_plan, options)
    stacked, _ = solve.Centred.of([dataclasses.replace(b, weight=b.weight / max(
        float(np.mean(b.b**2)), estimate.TINY)) for b in raw.blocks],
        source.records.n_trajectories).arrays()
    simple = sorted(range(n_terms), key=lambda k: library.terms[k].complexity)
    order = [*range(n_terms, stacked.shape[1]), *kept,
             *(k for k in simple if k not in kept)]
    collinear = [(j, tuple(sorted(p))) for j, p in best_subsets.collinear(stacked, order)]
    blocked = [(j, p) for j, p in collinear if j in kept or j >= n_terms]
    if blocked:
        raise FitError("cannot tell apart the terms kept (--keep, --damping) on these data: "
                       + "; ".join(f"{_name(library, j)} is collinear with "
                                   f"{', '.join(_name(library, k) for k in p)}"
                                   for j, p in blocked))
    return collinear, fit_plan


def choose(data: Any, options: SelectOptions, *, reading: Mapping[str, Any] | None = None,
           damping: str | Sequence[str] | None = "none",
           progress: Callable[[str], None] | None = None) -> Choice:
    """Search the library's subsets on the records in `data`, read with `reading` (the
    reading and velocity keywords of `hamid.fit`, `READING_KEYWORDS`), with no refit (see
    `select`)."""
    if any(os.fspath(d) == "-" for d in (data if isinstance(data, list | tuple) else [data])
           if isinstance(d, str | os.PathLike)):
        raise UsageError("select reads the data twice (to choose, then to refit): give a "
                         "file, not standard input")
    fit_options = FitOptions(**(reading or {}), damping=damping)
    source = _library_source(data, options.library, fit_options)
    m, records = source.model, source.records
    library = Library.of(m)
    kept = library.find(options.keep)
    forces = m.dissipative(fit_options.damping)
    collinear, fit_plan = _collinear(source, library, kept, forces, fit_options)
    n_terms = len(library.terms)
    dropped = {j for j, _ in collinear}
    unknowns = Unknowns.of(m, forces.names,
                           {library.terms[j].parameter: 0.0 for j in dropped})
    _, fit_plan, rows = estimate.fit_rows(source, unknowns, forces, fit_plan, fit_options, None)
    solved = estimate.least_squares(rows.blocks, unknowns.free_names, records.n_trajectories)
    window_group = None if rows.windows is None else rows.windows.group
    fraction = best_subsets.effective_fraction(solved, rows.blocks, window_group)
    grid = best_subsets.Design.of(solved, rows.blocks, fraction)
    columns_of = [k for k in range(n_terms) if k not in dropped] + [None] * len(forces.names)
    forced = [c for c, k in enumerate(columns_of) if k is None or k in kept]
    free = [c for c, k in enumerate(columns_of) if k is not None and k not in kept]
    ranking = best_subsets.search(grid, forced, free, options.criterion)
    shares = None
    if options.stability:
        check_replicates("--stability", options.stability, len(grid.unit))
        probability = best_subsets.inclusion(design=grid, forced=forced, free=free,
                                             criterion=options.criterion,
                                             replicates=options.stability, seed=options.seed,
                                             progress=progress)
        shares = {columns_of[c]: float(p) for c, p in zip(free, probability, strict=True)}
        shares.update({k: 1.0 for k in kept})
        shares = dict(sorted(shares.items()))
    chosen = tuple(sorted(columns_of[c] for c in ranking.chosen.columns
                          if columns_of[c] is not None))
    return Choice(library=library, options=options, chosen=chosen, kept=tuple(kept),
                  collinear=tuple(collinear), ranking=ranking, columns=tuple(columns_of),
                  inclusion=shares, kind=fit_plan.kind, n_rows=grid.n_rows,
                  n_effective=grid.n_effective)


def _name(library: Library, k: int) -> str:
    return library.terms[k].text if k < len(library.terms) else "a damping coefficient"


def select(data: Any, library: str | os.PathLike[str] | Model | None = None, *,
           keep: Sequence[str] = (), criterion: str = "bic", stability: int = 0,
           seed: int | None = 0, damping: str | Sequence[str] | None = "none",
           progress: Callable[[str], None] | None = None, **reading: Any) -> Selection:
    """Choose the terms of the energy from a library, and refit the chosen model.

    Parameters
    ----------
    data : path, list of paths, or pandas.DataFrame
        Recorded free oscillations, as `hamid.fit` reads them (not standard input: the
        data are read twice).
    library : str, path or Model, optional
        ``poly:N:D`` (every monomial of degree 2..D over the data's coordinates, unit
        kinetic energy), a TOML model file or a Model whose every parameter is a candidate
        term; by default ``poly:N:4``.
    keep : list of str
        Terms always in, by expression (``"u1**2"``) or parameter name.
    criterion : {"bic", "aic", "cv"}
        BIC or AIC on the effective number of rows, or blocked cross-validation over
        windows.
    stability : int
        Moving-block bootstrap replicates for each term's inclusion probability (0: none).
    seed : int or None
        Seed of the replicates (the same seed, the same probabilities).
    damping
        As for `hamid.fit`; damping coefficients are always in.
    **reading
        How the data are read and their velocities found, as for `hamid.fit`: ``columns``,
        ``time``, ``time_unit``, ``trajectory``, ``scale``, ``gaps``, ``format``,
        ``delimiter``, ``decimal``, ``skip_rows``, ``units_row``; ``velocity``, ``window``,
        ``order``.

    Returns
    -------
    Selection
        ``.chosen`` (the terms), ``.fit`` (the refit's FitResult, intervals conditional
        on the choice), ``.model`` and ``.model_file()`` (a TOML model of the chosen
        terms), ``.to_dict()`` (``hamid.select/1``).

    Examples
    --------
    >>> hamid.select("sample_data/duffing.csv", "poly:1:4").chosen
    ['x**2', 'x**4']
    """
    from hamid.api import fit

    unknown = sorted(set(reading) - set(READING_KEYWORDS))
    if unknown:
        raise TypeError(f"select() got an unexpected keyword argument {unknown[0]!r}")
    options = SelectOptions(library, tuple(keep), criterion, stability, seed)
    choice = choose(data, options, reading=reading, damping=damping, progress=progress)
    if not choice.chosen:
        raise FitError(f"no term of the library {choice.library.name} is chosen: the "
                       "energy would have no parameter to fit")
    model = choice.library.submodel(choice.chosen, f"{choice.library.name} selected")
    result = fit(data, model, damping=damping, progress=progress, **reading)
    return Selection(choice, model, result)
