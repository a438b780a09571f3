"""Fits of a file read in chunks of rows, so that memory does not grow with its length.

Every pass reads the file again, chunk by chunk (Parquet batches, blocks of CSV text;
`loading.Chunked`):

- ``energy``: the first pass accumulates each trajectory's triangular factor of its
  energy rows (`solve.Factor`), which gives the parameters and levels; the second the
  residual summary and the sums of the standard errors (`uncertainty.ScoreSums`); ``hac``
  takes a third, with the bandwidth found in the second.
- ``weak`` and ``joint``: the second pass builds the window rows, carrying each
  trajectory's unfinished windows into the next chunk, and writes them to a temporary
  file (one record per window: its energy row in joint and its weak rows). The fit then
  passes over that file: one pass gives each block's triangular factors, which give the
  estimates at any balance of the blocks (`estimate.balance`); each covariance the
  balance tries takes two more (``hac``: bandwidth, then meat).

Both return the `estimate.LinearFit` that the fit in memory returns for the same rows
(equal up to rounding; tested to 1e-10), scored by the same `estimate.Scores`.
`linear_fit` takes either source, whole (`estimate.fit_rows`) or in chunks, and says
which checks of the fit a pass in chunks cannot make.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from hamid.data import readers
from hamid.data.loading import Chunked, Loaded, Source
from hamid.data.records import Records, runs
from hamid.errors import DataError
from hamid.linear import design, estimate, noise_free, solve, uncertainty
from hamid.linear.design import Block, RowKind
from hamid.linear.estimate import LinearFit, ResidualSums, Rows, Scores
from hamid.linear.plan import FitPlan
from hamid.linear.unknowns import Unknowns
from hamid.model.dissipation import Dissipation
from hamid.options import FitOptions

__all__ = ["CHUNKED_SKIPS", "LinearStep", "energy_rows", "fit_chunks", "linear_fit"]


# What a fit read in chunks cannot make or keep, and why: (check, reason), in the report's
# `checks_skipped` (docs/output.md).
CHUNKED_SKIPS = (
    ("noise check", "it estimates the noise from the median of each trajectory's differences "
     "and compares least squares with adjusted least squares on every sample's rows, which "
     "need the records in memory; read the file whole (Python: in_memory=True; the command "
     "line: --residuals FILE)"),
    ("residuals per sample", "they are as long as the file; read it whole to keep them "
     "(Python: in_memory=True, result.samples; the command line: --residuals FILE)"),
    ("records for plotting", "the panels over the data (energy, residuals, phase, motion) "
     "need the records in memory; hamid plot REPORT DATA reads the file again for them"),
)


@dataclasses.dataclass(frozen=True)
class LinearStep:
    """The linear fit of a source and its plan; the rows fitted when the records are in
    memory (None in chunks), and the checks of the fit that could not be made, each
    (check, reason)."""

    fit: LinearFit
    plan: FitPlan
    rows: Rows | None
    energy_pieces: Callable[[], Iterable[Block]]   # every sample's energy rows, in pieces
    skipped: tuple[tuple[str, str], ...]


def linear_fit(source: Source, unknowns: Unknowns, damping: Dissipation, plan: FitPlan,
               options: FitOptions, sigma: Any) -> LinearStep:
    """The linear fit of the records in memory (`estimate.fit_rows`) or of a file a pass
    at a time (`fit_chunks`: no damping, no noise weighting, and no noise check)."""
    if isinstance(source, Loaded):
        fit, plan, rows = estimate.fit_rows(source, unknowns, damping, plan, options, sigma)
        return LinearStep(fit, plan, rows, rows.pieces, ())
    assert isinstance(source, Chunked) and not damping and sigma is None
    fit, plan = fit_chunks(source, unknowns, plan, options)
    rows_of = energy_rows(source, unknowns)
    return LinearStep(fit, plan, None, lambda: (rows_of(records, row) for records, row
                                                in source.rows("residual summary")),
                      CHUNKED_SKIPS)


def energy_rows(source: Chunked, unknowns: Unknowns) -> Callable[[Records, int], Block]:
    """The energy rows of a chunk (its records and first row), fixed parameters held;
    a term that is not finite is an error naming the file's row."""
    names = list(unknowns.names)

    def rows(records: Records, first_row: int) -> Block:
        block = design.energy_block(source.model, records)
        design.check_finite(block, lambda r: source.locate(first_row + r), names)
        return unknowns.hold_fixed(block)

    return rows


def fit_chunks(source: Chunked, unknowns: Unknowns, plan: FitPlan,
               options: FitOptions) -> tuple[LinearFit, FitPlan]:
    """The linear fit of the chunks, and the plan (energy rows when `auto` finds too few
    windows)."""
    rows = energy_rows(source, unknowns)
    if plan.kind != RowKind.ENERGY:
        fitted, plan = _windowed(source, rows, plan, unknowns, options)
        if fitted is not None:
            return fitted, plan
    return _energy(source, rows, unknowns.free_names, options.cov), plan


def _energy(source: Chunked, energy_rows: Callable[[Records, int], Block], names: list[str],
            cov: str) -> LinearFit:
    """The energy method in three passes: factor, residuals and bandwidth, meat."""
    p = len(names)
    factor = solve.Factor(p, 0)
    for records, row in source.rows("energy rows"):
        factor.add(energy_rows(records, row))
    J = len(source.labels)
    factor.grow(J)
    solution = solve.solve_factor(factor.centred(), np.sqrt(factor.raw_squares),
                                  factor.n_rows, names, n_levels=J)
    scores = Scores(solution.theta, solution.inverse, *factor.level_means, factor.total_weight)
    residuals, misfit = ResidualSums(scores.h), noise_free.Misfit(J)

    def score_pass(sums: uncertainty.ScoreSums) -> None:
        for records, row in source.rows("standard errors"):
            block = energy_rows(records, row)
            first = sums.bandwidth is None   # the first pass (hac: the one finding the bandwidth)
            if first:
                residuals.add(block, block.A @ scores.theta - block.b - scores.h[block.group])
            scores.feed(sums, [block], [1.0], None, misfit=misfit if first else None)

    sums, automatic = uncertainty.fed_sums(cov, p, J, score_pass)
    c = sums.covariance(factor.n_rows - p - J, automatic=automatic)
    covariance, description = misfit.widened(c.theta, c.description, solution.inverse)
    stats = residuals.stats(source.labels)
    h_stderr = np.sqrt(np.clip(estimate.level_variance(c, factor.level_means[0]), 0, None))
    return LinearFit(theta=solution.theta, covariance=covariance, description=description, df=c.df,
                     h=scores.h, h_stderr=h_stderr, block_variance=None,
                     block_stats={"energy": {"n_rows": int(residuals.n.sum()),
                                             "rms": stats["rms"],
                                             "max_abs": stats["max_abs"]}},
                     conditioning=solve.factor_conditioning(factor, names, source.labels),
                     block_conditions=None, energy_means=factor.level_means,
                     sizes=residuals.n.astype(np.int64), residuals=residuals)


def _windowed(source: Chunked, energy_rows: Callable[[Records, int], Block], plan: FitPlan,
              unknowns: Unknowns, options: FitOptions) -> tuple[LinearFit | None, FitPlan]:
    """Weak and joint fits: window rows built chunk by chunk into a temporary file, then
    fitted in passes over it (`_fit_windows`); no fit, and the energy rows' plan, when
    there are too few windows for `auto`."""
    m, window, kind = source.model, plan.window, plan.kind
    N = len(m.coordinates)
    layout = ([(RowKind.ENERGY, 1, True)] if kind == RowKind.JOINT else []
              ) + [(RowKind.WEAK, N, False)]
    store = _WindowRows(layout, len(unknowns.free), source.table.name)
    totals: dict[int, np.ndarray] = {}   # sums of A, b and the count of each trajectory
    quadrature = estimate.QuadratureError(len(unknowns.free))
    held: _Held | None = None

    def emit(held: _Held, ended: bool) -> None:
        first, last, held.next = design.window_ranges(
            held.records.t, window, origin=held.origin, skip=held.next, ended=ended)
        if len(first):
            spans = design.windows_at(held.records, first, last,
                                      np.full(len(first), held.j), window)
            weak = unknowns.hold_fixed(design.weak_block(m, held.records, spans))
            quadrature.add(weak, unknowns.hold_fixed(
                design.weak_quadrature_error(m, held.records, spans)))
            store.append([design.window_means(held.rows, spans), weak] if kind == RowKind.JOINT
                         else [weak])
        # Keep the samples from the first sample of the next window on.
        keep = int(np.searchsorted(held.records.t, held.origin + held.next * window
                                   * design.WINDOW_STEP))
        held.records = held.records.slice(keep, None)
        held.rows = held.rows.slice(keep, None)

    with store:
        for records, row in source.rows("window rows"):
            rows = energy_rows(records, row)
            for j, start, stop in runs(records.group):
                piece, piece_rows = records.slice(start, stop), rows.slice(start, stop)
                total = totals.setdefault(j, np.zeros(rows.A.shape[1] + 2))
                total += np.r_[piece_rows.A.sum(axis=0), piece_rows.b.sum(), stop - start]
                if held is not None and held.j != j:
                    emit(held, ended=True)
                    held = None
                if held is None:
                    held = _Held(j, float(piece.t[0]), 0, piece, piece_rows)
                else:
                    held.records = Records(np.vstack([held.records.X, piece.X]),
                                           np.concatenate([held.records.t, piece.t]),
                                           np.concatenate([held.records.group, piece.group]),
                                           ())
                    held.rows = _concatenate([held.rows, piece_rows])
                emit(held, ended=False)
        if held is not None:
            emit(held, ended=True)
        J = len(source.labels)
        plan = plan.check_windows(store.n_windows, unknowns.free_names, J, options)
        if plan.kind == RowKind.ENERGY:
            return None, plan
        sizes = np.array([totals[j][-1] for j in range(J)], dtype=np.int64)
        energy_means = np.array([totals[j][:-1] / totals[j][-1] for j in range(J)])
        return _fit_windows(store=store, kind=kind, names=unknowns.free_names,
                            labels=source.labels, cov=options.cov, sizes=sizes,
                            energy_means=(energy_means[:, :-1], energy_means[:, -1]),
                            quadrature=quadrature), plan


class _WindowRows:
    """The rows of a weak or joint fit in a temporary file, a record per window: the rows
    of each block it has in the window (`layout`: kind, rows per window, has a level),
    each row A, b and weight, then the window's trajectory and time. The fit reads them
    back a chunk of windows at a time, so that memory does not grow with the file."""

    CHUNK_WINDOWS = 1 << 14

    def __init__(self, layout: list[tuple[str, int, bool]], p: int, source: str) -> None:
        self.layout, self.p, self.source = layout, p, source
        self.width = sum(rows for _, rows, _ in layout) * (p + 2) + 2
        self.n_windows = 0
        self.file: Any = None

    @property
    def has_levels(self) -> bool:
        """Whether some block's rows carry their trajectory's energy level (joint)."""
        return any(level for _, _, level in self.layout)

    def __enter__(self) -> _WindowRows:
        import tempfile

        try:
            self.file = tempfile.TemporaryFile()
        except OSError as exc:
            raise self._unwritable(exc) from exc
        return self

    def _unwritable(self, exc: OSError) -> DataError:
        import tempfile

        return DataError(f"{self.source}: cannot keep its window rows in a temporary file in "
                         f"{tempfile.gettempdir()!r}: {readers.os_reason(exc)} (the environment "
                         "variable TMPDIR names another folder)")

    def __exit__(self, *_: object) -> None:
        self.file.close()

    def append(self, blocks: list[Block]) -> None:
        """The rows of the same windows, one block per entry of the layout."""
        n = blocks[0].n_rows // self.layout[0][1]
        record = np.empty((n, self.width))
        column = 0
        for block, (_, rows, _) in zip(blocks, self.layout, strict=True):
            width = rows * (self.p + 2)
            record[:, column:column + width] = np.column_stack(
                [block.A, block.b, block.weight]).reshape(n, width)
            column += width
        first = self.layout[0][1]
        record[:, -2], record[:, -1] = blocks[0].group[::first], blocks[0].time[::first]
        try:
            self.file.write(record.data)
        except OSError as exc:
            raise self._unwritable(exc) from exc
        self.n_windows += n

    def chunks(self) -> Iterator[tuple[list[Block], np.ndarray]]:
        """Each chunk's blocks, as the layout lists them, and the trajectory of each window."""
        self.file.seek(0)
        left, p = self.n_windows, self.p
        while left:
            n = min(left, self.CHUNK_WINDOWS)
            record = np.empty((n, self.width))
            self.file.readinto(record.data)
            left -= n
            group, time = record[:, -2].astype(np.int64), record[:, -1]
            blocks, column = [], 0
            for kind, rows, has_level in self.layout:
                values = record[:, column:column + rows * (p + 2)].reshape(n * rows, p + 2)
                column += rows * (p + 2)
                blocks.append(Block(kind=kind, A=values[:, :p], b=values[:, p],
                                    group=np.repeat(group, rows), time=np.repeat(time, rows),
                                    weight=values[:, p + 1], has_level=has_level))
            yield blocks, group


def _fit_windows(store: _WindowRows, kind: str, names: list[str],
                 labels: tuple[Any, ...], cov: str, sizes: np.ndarray,
                 energy_means: tuple[np.ndarray, np.ndarray],
                 quadrature: estimate.QuadratureError) -> LinearFit:
    """The fit of the stored window rows as `estimate.fit_rows` makes it of the same rows
    in memory: the blocks' triangular factors from one pass give the estimates for any
    balance of the blocks, and each covariance takes one pass (two for ``hac``); the
    weak rows' quadrature error from the sums fed as they were made."""
    p, J = len(names), len(labels)
    factors = [solve.Factor(p, J) for _ in store.layout]
    squares = np.zeros(len(store.layout))   # sum w b^2 of each block
    for blocks, _ in store.chunks():
        for k, (factor, block) in enumerate(zip(factors, blocks, strict=True)):
            factor.add(block)
            squares[k] += block.weight @ block.b**2

    def solved(scales: list[float]) -> tuple[solve.Factor, solve.Solution]:
        joined = solve.Factor.joined([f.scaled(c) for f, c in zip(factors, scales,
                                                                  strict=True)])
        return joined, solve.solve_factor(joined.centred(), np.sqrt(joined.raw_squares),
                                          joined.n_rows, names,
                                          n_levels=J if store.has_levels else 0)

    fits: dict[float, _WindowFit] = {}   # the hac fit at each ratio the balance tried
    if len(factors) == 1:
        ratio, scales, block_variance = None, [1.0], None
    else:
        variance = {}   # each block's mean w r^2 in a fit of its own
        for (block_kind, _, level), factor, square in zip(store.layout, factors, squares,
                                                           strict=True):
            R = factor.centred()

            def alone(R: np.ndarray = R, level: bool = level,
                      factor: solve.Factor = factor) -> float:
                solve.solve_factor(R, np.sqrt(factor.raw_squares), factor.n_rows, names,
                                   n_levels=J if level else 0)
                return float(R[p, p] ** 2 if R.shape[0] > p else 0.0) / factor.n_rows

            variance[block_kind] = estimate.own_variance(alone, square / factor.n_rows)
        kinds = [block_kind for block_kind, _, _ in store.layout]

        def ratio_scales(ratio: float) -> list[float]:
            return [ratio / variance[kinds[0]], *(1 / variance[k] for k in kinds[1:])]

        def spread(ratio: float) -> float:
            fits[ratio] = _window_fit(store, *solved(ratio_scales(ratio)), ratio_scales(ratio),
                                      "hac", names, J)
            return estimate.log_spread(fits[ratio].covariance.theta)

        ratio, block_variance = estimate.balance(variance, kinds[0], spread)
        scales = ratio_scales(ratio)
    joined, solution = solved(scales)
    fit = fits.get(ratio) if cov == "hac" else None
    if fit is None:
        fit = _window_fit(store=store, joined=joined, solution=solution, scales=scales, cov=cov,
                          names=names, J=J)
    c = fit.covariance
    means_A = joined.level_means[0]
    h, h_stderr = estimate.fitted_levels(kind, solution.theta, fit.h,
                                         estimate.level_variance(c, means_A), energy_means)
    block_stats = {block_kind: {"n_rows": int(n), "rms": float(np.sqrt(square / n)),
                                "max_abs": float(largest)}
                   for (block_kind, _, _), (n, square, largest) in zip(
                       store.layout, fit.residuals, strict=True)}
    cond = solve.factor_conditioning(joined, names, labels)
    each = ({block_kind: solve.factor_conditioning(factor, names, labels).condition_number
             for (block_kind, _, _), factor in zip(store.layout, factors, strict=True)}
            if len(factors) > 1 else None)
    covariance, description = fit.misfit.widened(c.theta, c.description, solution.inverse)
    shift = quadrature.shift(solution.theta, solution.inverse, scales[-1])   # weak: last
    covariance, description = estimate.with_discretization(covariance, description, shift)
    return LinearFit(theta=solution.theta, covariance=covariance, description=description, df=c.df,
                     h=h, h_stderr=h_stderr, block_variance=block_variance,
                     block_stats=block_stats, conditioning=cond, block_conditions=each,
                     energy_means=energy_means, sizes=sizes, discretization=shift)


@dataclasses.dataclass(frozen=True)
class _WindowFit:
    """A covariance of the stored window rows' fit, its levels, the number of rows,
    sum of squared residuals and largest residual of each block, and its misfit."""

    covariance: uncertainty.Covariance
    h: np.ndarray
    residuals: list[tuple[int, float, float]]
    misfit: noise_free.Misfit


def _window_fit(store: _WindowRows, joined: solve.Factor, solution: solve.Solution,
                scales: list[float], cov: str, names: list[str], J: int) -> _WindowFit:
    """The covariance of kind `cov` of the fit `solution` of the stored rows weighted by
    `scales`: ``hac`` on the series of each window's summed scores (`estimate.Scores`)."""
    p = len(names)
    scores = Scores(solution.theta, solution.inverse, *joined.level_means,
                    joined.total_weight)
    by_window = cov == "hac"
    residuals: list[tuple[int, float, float]] = []   # rows, squares, largest of each block
    misfit = noise_free.Misfit(J)

    def scored(sums: uncertainty.ScoreSums) -> None:
        nonlocal misfit
        residuals[:] = [(0, 0.0, 0.0)] * len(store.layout)
        misfit = noise_free.Misfit(J)
        for blocks, group in store.chunks():
            stats = scores.feed(sums, blocks, scales, group if by_window else None,
                                misfit=misfit)
            residuals[:] = [(n + m, square + more, max(largest, top)) for (n, square, largest),
                            (m, more, top) in zip(residuals, stats, strict=True)]

    sums, automatic = uncertainty.fed_sums(cov, p, J, scored)
    fitted = p + (J if store.has_levels else 0)
    n_rows = sum(n for n, _, _ in residuals)
    if not by_window:
        return _WindowFit(sums.covariance(n_rows - fitted, automatic=automatic), scores.h,
                          residuals, misfit)
    c = sums.covariance(store.n_windows - fitted, automatic=automatic)
    return _WindowFit(estimate.windows_covariance(c, store.n_windows), scores.h, residuals,
                      misfit)


@dataclasses.dataclass
class _Held:
    """The open trajectory of a chunked weak/joint pass: its samples (and energy rows)
    from the first sample of its next window on, still to be cut into windows."""

    j: int
    origin: float    # the trajectory's first time, from which windows are counted
    next: int        # number of its next window
    records: Records
    rows: Block


def _concatenate(blocks: list[Block]) -> Block:
    first = blocks[0]
    return dataclasses.replace(
        first, A=np.vstack([b.A for b in blocks]), b=np.concatenate([b.b for b in blocks]),
        group=np.concatenate([b.group for b in blocks]),
        time=np.concatenate([b.time for b in blocks]),
        weight=np.concatenate([b.weight for b in blocks]))
