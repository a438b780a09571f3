"""The trajectory refinement's integrations: batches of segments, each integrated as one
vectorised system, reduced to their Gauss-Newton blocks, here or in worker processes.

A `Batch` holds segments and, for each, the copies its forward-difference Jacobian needs
(as is, each initial-state component perturbed, each free parameter perturbed). `blocks`
integrates them together with `hamid.refine.dop853` (the copies share the adaptive steps, so
their differences carry almost no integration error) and returns each segment's weighted
misfit and its Jacobian's normal equations. Given the parameters, batches are independent:
`run` maps them over the workers of the enclosing `parallel` block, started at the first
round worth them and kept for the rounds after (the Gauss-Newton iterations, refits and
the held-out check of one refinement). What a batch holds never depends on the workers,
so neither do the results.
"""

from __future__ import annotations

import bisect
import contextlib
import contextvars
import copyreg
import dataclasses
import functools
import io
import pickle
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.executor import Pool, Workers, started
from hamid.model.dynamics import Dynamics, Inputs
from hamid.refine import dop853

__all__ = ["Batch", "Blocks", "IntegrationFailed", "SampledInputs", "Tolerance", "blocks",
           "common_times", "parallel", "responses", "run"]

Array = npt.NDArray[np.float64]

# Values integrated in one round (copies x states x samples, summed over its batches) from
# which the batches go to worker processes: about 270,000 samples of two degrees of
# freedom. Starting two costs 0.2-0.4 s and each round moves its batches, while a
# refinement makes four rounds: on a 2-core machine at load 0.3-1, two processes made
# peng-quadratic's refinement 0.89-0.98x as fast as one on 160,000 samples, 0.92x on
# 200,000, 0.97x on 240,000, 1.18x on 280,000, 1.15-1.23x on 400,000, 1.42-1.44x on
# 640,000 (`tests/benchmarks/crossover.py`; docs/scaling.md).
PARALLEL_VALUES = 12_000_000
# Segments whose Gauss-Newton blocks are formed together (`blocks`): enough that numpy's
# calls are few, few enough that their arrays stay in cache.
GATHERED = 32
# Central-difference step of the rates' derivatives by an input, of its largest value
INPUT_STEP = 1e-6


class IntegrationFailed(Exception):
    """A batch could not be integrated; the reason is the text."""


@dataclass(frozen=True)
class Tolerance:
    """How a batch is integrated: local errors within atol + rtol |y| (atol per variable);
    sample times closer than `resolution` integrated to once; at most `steps_per_sample`
    steps per integration time, plus `min_steps`."""

    rtol: float
    atol: Array
    resolution: float
    steps_per_sample: int
    min_steps: int


@dataclass(frozen=True, eq=False)
class SampledInputs:
    """The recorded inputs of a batch's segments: each segment's sample times from its
    start (`tau`, through the sample a tie compares with) and inputs there (m, n_inputs).

    Between the samples the inputs follow a cubic spline (not-a-knot): a DAQ samples a
    band-limited input, it does not hold it, and a cubic errs by O(dt^4) where linear
    interpolation errs by O(dt^2). Segments sampled alike (the usual case) share one spline
    of all their columns, evaluated once per integrator stage; past a segment's last
    sample its last value is held (no residual is taken there).
    """

    tau: Sequence[Array]
    values: Sequence[Array]
    # made on first use and kept for the refinement's passes (`part`, `spline`)
    _parts: dict[tuple[int, int], SampledInputs] = field(
        default_factory=dict, init=False, repr=False)
    _splines: dict[float, Any] = field(default_factory=dict, init=False, repr=False)

    def __getstate__(self) -> dict[str, Any]:
        """Pickled without the parts and splines made here (a worker makes its own)."""
        return {**self.__dict__, "_parts": {}, "_splines": {}}

    def part(self, lo: int, hi: int) -> SampledInputs:
        """Segments lo:hi, made once: a batch's spline is then made once per refinement
        (`spline`), not at every pass (1 of its 1.3 ms for 16 segments of 1250 samples)."""
        if (lo, hi) not in self._parts:
            self._parts[lo, hi] = SampledInputs(self.tau[lo:hi], self.values[lo:hi])
        return self._parts[lo, hi]

    def spline(self, resolution: float) -> Any:
        """The spline through every segment's inputs on the `grid`: a scipy CubicSpline of
        the `table` as (len(grid), n_inputs * B), made once per resolution."""
        from scipy.interpolate import CubicSpline

        if resolution not in self._splines:
            grid = self.grid(resolution)
            self._splines[resolution] = CubicSpline(
                grid, self.table(grid, resolution).reshape(len(grid), -1), axis=0)
        return self._splines[resolution]

    def grid(self, resolution: float) -> Array:
        """The times the batch's spline has its knots at (`common_times`)."""
        return common_times(list(self.tau), resolution)[0]

    def _placed(self, b: int, grid: Array, resolution: float) -> tuple[int, bool]:
        """How many knots segment `b`'s samples reach, and whether they are its samples."""
        tau = self.tau[b]
        inside = int(np.searchsorted(grid, tau[-1], side="right"))
        # (np.allclose's checks cost more than the comparison, at every segment and pass)
        return inside, inside == len(tau) and bool(
            np.max(np.abs(tau - grid[:inside])) <= resolution)

    def table(self, grid: Array, resolution: float) -> Array:
        """Every segment's inputs at the knots `grid` (len(grid), n_inputs, B): its samples
        where they are the knots, else its own spline there; its last value held after."""
        from scipy.interpolate import CubicSpline

        table = np.empty((len(grid), self.values[0].shape[1], len(self.tau)))
        for b, (tau, values) in enumerate(zip(self.tau, self.values, strict=True)):
            inside, alike = self._placed(b, grid, resolution)
            table[:inside, :, b] = values if alike else CubicSpline(tau, values)(grid[:inside])
            table[inside:, :, b] = table[inside - 1, :, b]
        return table

    def by_samples(self, b: int, grid: Array, resolution: float, gradient: Array) -> Array:
        """A `gradient` (len(grid), ...) by segment `b`'s column of the `table` taken to
        its samples (m, ...): the table's dependence on them, transposed."""
        from hamid.refine.input_noise import spline_gradient

        inside, alike = self._placed(b, grid, resolution)
        by_table = gradient[:inside].copy()
        by_table[inside - 1] += gradient[inside:].sum(axis=0)
        if alike:
            return by_table
        shape = by_table.shape
        return spline_gradient(self.tau[b], grid[:inside], by_table.reshape(inside, -1)
                               ).reshape(len(self.tau[b]), *shape[1:])

    def path(self, copies: int, resolution: float) -> Inputs:
        """u(t) of every integrated state, (n_inputs, B * copies), each segment's inputs
        repeated for its copies (the states' order in `blocks`), as `Dynamics.at` takes
        them, or of one segment shared by any number of states; times closer than
        `resolution` are one (`common_times`)."""
        n_inputs = self.values[0].shape[1]
        # the spline's pieces, evaluated by hand: scipy's call costs more than the rest of
        # an integrator stage (tests/benchmarks/driven_refinement.py)
        spline = self.spline(resolution)
        pieces = len(spline.x) - 1
        # each piece's (4, n_inputs * B * copies) coefficients, each segment's repeated for
        # its copies once here, not at every stage
        c = np.ascontiguousarray(np.repeat(
            spline.c.transpose(1, 0, 2).reshape(pieces, 4, n_inputs, -1, 1), copies,
            axis=4).reshape(pieces, 4, -1))
        by_piece, size = list(c), c.shape[2]   # views made once, not at every stage
        bounds = spline.x.tolist()
        powers = np.ones(4)   # h^3, h^2, h, 1: filled in place, cheaper than a new array

        def u(t: float, out: Array) -> None:
            # the piece of t, the first or last beyond the knots: searched at every call,
            # since an integrator step spans tens of samples and its stages jump between
            i = bisect.bisect_right(bounds, t, 1, pieces) - 1
            h = t - bounds[i]
            powers[0], powers[1], powers[2] = h * h * h, h * h, h
            # np.dot: a quarter cheaper than @ on a vector and a matrix this small
            if out.size == size:
                np.dot(powers, by_piece[i], out=out.reshape(-1))
            else:   # one segment's inputs, shared by every state (a prediction's starts)
                out[:] = np.dot(powers, by_piece[i]).reshape(n_inputs, -1)

        return u


@dataclass(frozen=True, eq=False)
class Batch:
    """Segments integrated together, each as `starts.shape[0]` copies.

    `starts` (copies, B, 2N) and `weights` (n_weights, copies, B) are every copy's initial
    state and weights (1, theta, damping); `steps` the perturbation of each copy past the
    first, by which its difference from the first is divided. `ends`, if given, are a time
    of each segment (from its start, none before its samples) whose state and derivatives
    `blocks` returns too, without a residual (multiple shooting's continuity conditions).
    With `keep` (a driven model, with `ends` and a copy per initial-state component),
    `blocks` returns its integrated values too, from which `responses` gives what each
    recorded input sample moves the scores and the end states by.
    """

    dynamics: Dynamics
    tau: Sequence[Array]        # each segment's times from its start
    measured: Sequence[Array]   # each segment's samples (m, 2N), accelerations after (m, 3N)
    weight: Array               # 1 / noise of each variable (and acceleration)
    starts: Array
    weights: Array
    steps: Array
    tolerance: Tolerance
    ends: Array | None = None
    inputs: SampledInputs | None = None
    keep: bool = False

    @property
    def values(self) -> int:
        """Values integrated: copies x states x samples."""
        copies, _, n_states = self.starts.shape
        return copies * n_states * sum(len(x) for x in self.tau)

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled for a worker: the equations as bytes without their cached properties
        (compiled functions, which do not pickle), which the worker unpickles and compiles
        once for every batch and round that brings the same bytes (`_equations`)."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        fields["dynamics"] = _without_caches(self.dynamics)
        return _received, (fields,)


def _received(fields: dict[str, Any]) -> Batch:
    """Helper run by a worker: the batch, its equations unpickled once per process."""
    return Batch(**{**fields, "dynamics": _equations(fields["dynamics"])})


@functools.lru_cache(maxsize=4)
def _equations(pickled: bytes) -> Dynamics:
    return pickle.loads(pickled)


class _CachesLeftOut(pickle.Pickler):
    """Pickles objects without the values of their cached properties: derived, and
    derived again on first use."""

    def reducer_override(self, obj: Any) -> Any:
        cached = _cached_properties(type(obj)) & getattr(obj, "__dict__", {}).keys()
        if not cached:
            return NotImplemented
        state = {k: v for k, v in obj.__dict__.items() if k not in cached}
        return copyreg.__newobj__, (type(obj),), state


@functools.cache
def _cached_properties(cls: type) -> frozenset[str]:
    return frozenset(name for klass in cls.__mro__ for name, value in vars(klass).items()
                     if isinstance(value, functools.cached_property))


def _without_caches(obj: Any) -> bytes:
    buffer = io.BytesIO()
    _CachesLeftOut(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return buffer.getvalue()


@dataclass(frozen=True)
class Blocks:
    """A batch's segments reduced: `cost` (B, 2N), each variable's weighted squared
    residuals; `H` (B, c, c) and `g` (B, c), J'J and J'r of each segment's Jacobian by its
    c perturbed copies (empty when there are none); with the batch's `ends`, `end` (B, 2N)
    each segment's state there and `E` (B, 2N, c) its derivatives by the copies; with the
    batch's `keep`, `integrated`: the output times, the samples' and ends' indices into
    them and the values there (len(grid), variables, B, copies), for `responses`."""

    cost: Array
    H: Array
    g: Array
    end: Array | None = None
    E: Array | None = None
    integrated: tuple[Array, npt.NDArray[np.intp], Array] | None = None


def blocks(batch: Batch) -> Blocks:
    """The batch integrated and reduced; raises IntegrationFailed."""
    copies, B, n_states = batch.starts.shape
    tol = batch.tolerance
    times = list(batch.tau) if batch.ends is None else [*batch.tau, batch.ends]
    grid, where = common_times(times, tol.resolution)
    # the columns of the integrated system segment by segment, each segment's copies
    # together: the values of a few neighbouring segments are then one contiguous run
    motion = batch.dynamics.at(batch.weights.transpose(0, 2, 1).reshape(len(batch.weights), -1),
                               inputs=None if batch.inputs is None
                               else batch.inputs.path(copies, tol.resolution))
    try:
        values = dop853.integrate(
            motion, batch.starts.transpose(2, 1, 0).ravel(), grid, tol.rtol,
            np.repeat(tol.atol, copies * B), tol.steps_per_sample * len(grid) + tol.min_steps,
            end=max(float(np.max(t)) for t in times))   # grid[-1] may be a rounding earlier
    except dop853.TooManySteps as exc:
        raise IntegrationFailed("the integration needs too many steps: the model's motion "
                                "is stiff or blows up") from exc
    except dop853.IntegrationFailed as exc:
        raise IntegrationFailed(f"the integration failed ({exc})") from exc
    if not np.all(np.isfinite(values)):
        raise IntegrationFailed("the integrated motion is not finite")
    if len(batch.weight) > n_states:   # recorded accelerations: the equations' at the states
        rates = np.stack([motion(float(time), y) for time, y in zip(grid, values, strict=True)])
        values = np.concatenate([values.reshape(len(grid), n_states, B, copies),
                                 rates.reshape(len(grid), n_states, B, copies)[:, n_states // 2:]],
                                axis=1)
    values = values.reshape(len(grid), len(batch.weight), B, copies)
    weight, steps, c = batch.weight, batch.steps, copies - 1
    cost, H, g = np.empty((B, len(weight))), np.empty((B, c, c)), np.empty((B, c))
    offsets = np.cumsum([0, *map(len, batch.tau)])
    for lo, hi in _alike(where, offsets):
        # neighbouring segments sampled alike: (m, 2N, G, copies) gathered at once
        Y = values[where[offsets[lo]:offsets[lo + 1]], :, lo:hi]
        measured = np.stack(batch.measured[lo:hi], axis=-1)                     # (m, 2N, G)
        residual = (measured - Y[..., 0]) * weight[:, None]
        cost[lo:hi] = np.einsum("msg,msg->gs", residual, residual)
        if c == 0:
            continue
        # each variable's forward differences (G, 2N, c, m), weighed and divided by the
        # steps once their products are summed
        D = (Y[..., 1:1 + c] - Y[..., :1]).transpose(2, 1, 3, 0)
        products = np.matmul(D, D.transpose(0, 1, 3, 2))                        # (G, 2N, c, c)
        H[lo:hi] = np.einsum("gscd,s->gcd", products, weight**2) / np.outer(steps, steps)
        scores = np.matmul(D, residual.transpose(2, 1, 0)[..., None])[..., 0]   # (G, 2N, c)
        g[lo:hi] = np.einsum("gsc,s->gc", scores, weight) / steps
    offset = offsets[-1]
    if batch.ends is None:
        return Blocks(cost, H, g)
    at_ends = values[where[offset:], :n_states, np.arange(B)]       # (B, 2N, copies)
    end = at_ends[..., 0]
    return Blocks(cost, H, g, end, (at_ends[..., 1:1 + c] - end[..., None]) / batch.steps,
                  integrated=(grid, where, values) if batch.keep else None)


def responses(batch: Batch, integrated: tuple[Array, npt.NDArray[np.intp], Array],
              outputs: Array) -> list[Array]:
    """Each segment's change of combinations `outputs` (B, r, c + 2N) of its scores and
    end state by each of its input samples, (m, r, n_inputs), to first order
    (`hamid.refine.input_noise.response`), from the batch's `Blocks.integrated`: the values
    (len(grid), variables, B, copies) at the output times `grid`, `where` the samples' and
    ends' indices into it."""
    from hamid.refine.input_noise import Segment, response

    grid, where, values = integrated
    inputs = batch.inputs
    assert inputs is not None and batch.ends is not None
    copies, B, n_states = batch.starts.shape
    n_inputs, N = inputs.values[0].shape[1], n_states // 2
    # the rates' derivatives by the inputs at every output time, copy 0 (central differences)
    spline = inputs.spline(batch.tolerance.resolution)
    knots = spline.x
    u = spline(grid).reshape(len(grid), n_inputs, B).transpose(1, 0, 2).reshape(n_inputs, -1)
    states = values[:, :n_states, :, 0].transpose(1, 0, 2).reshape(n_states, -1)
    moved = u.copy()

    def moved_inputs(time: float, out: Array) -> None:
        out[:] = moved

    weights = batch.weights[:, 0]   # copy 0 of each segment, usually one set for all
    motion = batch.dynamics.at(weights[:, 0] if np.all(weights == weights[:, :1])
                               else np.tile(weights, (1, len(grid))), inputs=moved_inputs)
    B_all = np.zeros((len(grid), n_states, B, n_inputs))
    for k in range(n_inputs):
        step = INPUT_STEP * max(float(np.max(np.abs(u[k]))), 1e-300)
        moved[k] = u[k] + step
        up = motion.accelerations(states)
        moved[k] = u[k] - step
        down = motion.accelerations(states)
        moved[k] = u[k]
        B_all[:, N:, :, k] = ((up - down) / (2 * step)).reshape(N, len(grid), B).transpose(1, 0, 2)
    weight, steps = batch.weight, batch.steps
    offsets = np.cumsum([0, *map(len, batch.tau)])
    # segments sampled alike and ending alike, taken together
    groups: dict[tuple[bytes, int], list[int]] = {}
    for b in range(B):
        key = (where[offsets[b]:offsets[b + 1]].tobytes(), int(where[offsets[-1] + b]))
        groups.setdefault(key, []).append(b)
    out: list[Array] = [np.empty(0)] * B
    for members in groups.values():
        samples = where[offsets[members[0]]:offsets[members[0] + 1]]
        last = int(where[offsets[-1] + members[0]])
        Y = values[:last + 1, :, members]                                   # (G, var, S, copies)
        J = ((Y[samples, :, :, 1:] - Y[samples, :, :, :1]) / steps).transpose(2, 0, 1, 3)
        weighed = (J * (weight**2)[:, None]).swapaxes(2, 3)                 # (S, m, c, var)
        direct = None
        if len(weight) > n_states:   # accelerations: their residuals move with u itself
            direct = -weighed[..., n_states:] @ B_all[samples, N:][:, :, members].transpose(
                2, 0, 1, 3)
        phi = (Y[:, :n_states, :, 1:1 + n_states] - Y[:, :n_states, :, :1]) / steps[:n_states]
        moves = response(Segment(
            times=grid[:last + 1], phi=phi.transpose(2, 0, 1, 3),
            B=B_all[:last + 1, :, members].transpose(2, 0, 1, 3), samples=samples,
            products=weighed @ J[..., :n_states], direct=direct), knots, outputs[members])
        for b, move in zip(members, moves, strict=True):
            out[b] = inputs.by_samples(b, knots, batch.tolerance.resolution, move)
    return out


def _alike(where: npt.NDArray[np.intp], offsets: npt.NDArray[np.intp]
           ) -> Iterator[tuple[int, int]]:
    """Runs of at most GATHERED neighbouring segments (lo, hi) that sample the common
    times alike (the same indices into them: usually all but a trajectory's last)."""
    lo = 0
    for b in range(1, len(offsets)):
        if (b == len(offsets) - 1 or b - lo == GATHERED
                or not np.array_equal(where[offsets[lo]:offsets[lo + 1]],
                                      where[offsets[b]:offsets[b + 1]])):
            yield lo, b
            lo = b


def common_times(times: Sequence[Array], resolution: float) -> tuple[Array, npt.NDArray[np.intp]]:
    """The distinct times of all the arrays, those closer than `resolution` taken as one
    (the earliest), and the index into them of every time of the concatenated arrays."""
    joined = np.concatenate(times)
    order = np.argsort(joined, kind="stable")
    ordered = joined[order]
    starts = np.empty(len(ordered), dtype=bool)
    starts[0] = True
    starts[1:] = np.diff(ordered) > resolution
    where = np.empty(len(ordered), dtype=np.intp)
    where[order] = np.cumsum(starts) - 1
    return ordered[starts], where


class _Workers:
    """The workers of a `parallel` block, started at the first round worth them."""

    def __init__(self, workers: Workers, stack: contextlib.ExitStack):
        self.workers, self._stack = workers, stack
        self._pool: Pool | None = None

    def start(self) -> None:
        """Start the workers now, in the background, unless there is only this process."""
        if self.workers != Workers() and self._pool is None:
            self._pool = self._stack.enter_context(started(self.workers, __name__))
            self._pool.warm()

    def pool(self, batches: Sequence[Batch]) -> Pool | None:
        """The pool for a round of `batches`, or None to run it here: one batch, or too
        little work to pay for starting the processes (once started, they take any round
        of two batches or more: a batch's cost is more its steps than its values)."""
        if self.workers == Workers() or len(batches) < 2:
            return None
        if self._pool is None and sum(batch.values for batch in batches) < PARALLEL_VALUES:
            return None
        self.start()
        return self._pool


_current: contextvars.ContextVar[_Workers | None] = contextvars.ContextVar(
    "hamid.refine.integration workers", default=None)


@contextlib.contextmanager
def parallel(workers: Workers, expected: int = 0) -> Iterator[None]:
    """Rounds of batches `run` within the block go to `workers` when they are worth it;
    the processes start at the first such round, or at once when a round is `expected`
    to integrate PARALLEL_VALUES values or more (their start then goes on beside the
    work before the first round), and stop when the block ends."""
    with contextlib.ExitStack() as stack:
        workers_now = _Workers(workers, stack)
        if expected >= PARALLEL_VALUES:
            workers_now.start()
        token = _current.set(workers_now)
        try:
            yield
        finally:
            _current.reset(token)


def run(batches: Sequence[Batch]) -> Iterator[Blocks]:
    """Each batch's `blocks`, in order, each as soon as it and those before are done.

    In a `parallel` block, a round of at least two batches runs on its workers, which
    start at the first such round of PARALLEL_VALUES values or more; otherwise, or outside
    one, here.
    """
    current = _current.get()
    pool = None if current is None else current.pool(batches)
    return map(blocks, batches) if pool is None else pool.map(blocks, batches)
