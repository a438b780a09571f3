"""Running one function over many items, in this process, in local processes or on a Dask
cluster, with the results in the order of the items.

`Workers` says where (a small frozen config); `ordered_map` runs a picklable function over
the items there and yields each result as soon as it and those before it are done. Only a
bounded number of items is in flight at once, so 10^5 items take the memory of a few dozen.
`hamid fit --each` maps its fits with it; any work split into independent pieces can.
`started` keeps the workers from one map to the next, for work that comes in rounds (the
trajectory refinement maps its batches of segments once per Gauss-Newton iteration).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

from hamid.errors import HamidError, UsageError

__all__ = ["DASK_EXTRA", "SCHEDULER_VARIABLE", "Pool", "Workers", "available_cores",
           "check_address", "one_blas_thread", "ordered_map", "started"]

T = TypeVar("T")
R = TypeVar("R")

DASK_EXTRA = "pip install 'hamid[dask]'"
# Dask's own variable for the scheduler's address (dask.config's scheduler-address).
SCHEDULER_VARIABLE = "DASK_SCHEDULER_ADDRESS"
# Items in flight per worker: enough to keep every worker busy while an earlier, slower
# item holds back the results behind it.
_IN_FLIGHT_PER_WORKER = 4
# Seconds to wait for a Dask scheduler to answer.
_CONNECT_TIMEOUT = 10


def one_blas_thread() -> contextlib.AbstractContextManager[Any]:
    """A block in which BLAS (numpy's and scipy's, those loaded) runs on one thread
    (threadpoolctl). A fit's products are many and small (pieces of 2^16 rows by a few
    columns, the integrator's stages): threads gain little on them, and on busy cores
    lose much, waiting on each other. On two cores under a load of 2.8, 160,000 samples
    of peng-quadratic took 1.60 s with two threads and 0.53 s with one (`--method
    joint`), 2.33 and 1.34 s (auto); processes (`--jobs`) share the cores the same way."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1, user_api="blas")


def available_cores() -> int:
    """The cores this process may run on (its affinity, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


@dataclass(frozen=True, slots=True)
class Workers:
    """Where work runs: `jobs` local processes (1: this process), or the Dask cluster
    whose scheduler is at `scheduler` (``tcp://HOST:PORT``)."""

    jobs: int = 1
    scheduler: str | None = None

    def __post_init__(self) -> None:
        if self.jobs < 1:
            raise UsageError(f"--jobs must be at least 1, found {self.jobs}")
        if self.scheduler is not None:
            check_address(self.scheduler, "--scheduler")

    @classmethod
    def choose(cls, jobs: int | None, scheduler: str | None, n_items: int) -> Workers:
        """The workers for `n_items` items: a scheduler given, else `jobs` processes, else
        the scheduler of DASK_SCHEDULER_ADDRESS, else one process per core (never more
        than items)."""
        if jobs is not None and scheduler is not None:
            raise UsageError("--jobs and --scheduler exclude each other: --jobs runs local "
                             "processes, a cluster has its own workers")
        if jobs is None and scheduler is None:
            scheduler = os.environ.get(SCHEDULER_VARIABLE) or None
            if scheduler is not None:
                check_address(scheduler, SCHEDULER_VARIABLE)
        if scheduler is not None:
            return cls(scheduler=scheduler)
        return cls(jobs=max(1, min(jobs or available_cores(), n_items)))


# The schemes of Dask's addresses that reach another process (distributed.comm).
_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")


def check_address(address: str, where: str) -> None:
    """Refuse what cannot be a Dask scheduler's address, [SCHEME://]HOST:PORT, before a
    client is made: distributed refused 'notaurl' inside the Client, whose half-made
    object then printed a traceback 20 s later as it was collected."""
    scheme, separator, location = address.strip().partition("://")
    if not separator:
        scheme, location = "tcp", address.strip()
    host, colon, port = location.rpartition(":")
    if scheme not in _SCHEMES or not colon or not host.strip("[]") or not port.isdigit() \
            or not 0 < int(port) < 65536:
        raise UsageError(f"{where}: {address!r} is not a Dask scheduler address; expected "
                         f"tcp://HOST:PORT ({', '.join(_SCHEMES)})")


def ordered_map(function: Callable[[T], R], items: Iterable[T],
                workers: Workers) -> Iterator[R]:
    """``function(item)`` for each item, run by `workers`, yielded in the order of the items.

    `function` and the items must be picklable unless the work stays in this process
    (``Workers(jobs=1)``); an exception that `function` raises is raised here when its
    item's turn comes. Closing the iterator early, Ctrl-C or a signal cancels what has not
    run and stops the local processes.
    """
    with started(workers, function.__module__) as pool:
        yield from pool.map(function, items)


Submit = Callable[[Callable[[Any], Any], Any], Any]


class Pool:
    """Workers kept running from one map to the next (`started`): for work that comes in
    rounds, such as the iterations of a fit, where starting processes each round would
    cost more than the round."""

    def __init__(self, submit: Submit | None, capacity: int):
        self._submit, self.capacity = submit, capacity

    def map(self, function: Callable[[T], R], items: Iterable[T]) -> Iterator[R]:
        """``function(item)`` for each item, in the order of the items (`ordered_map`);
        closing the iterator early cancels the items not yet running."""
        if self._submit is None:
            yield from map(function, items)
            return
        submit = self._submit
        queue = iter(items)
        pending = deque(submit(function, item) for item in
                        itertools.islice(queue, _IN_FLIGHT_PER_WORKER * self.capacity))
        try:
            while pending:
                result = pending.popleft().result()
                for item in itertools.islice(queue, 1):
                    pending.append(submit(function, item))
                yield result
        finally:
            for future in pending:
                future.cancel()

    def warm(self) -> None:
        """Start the workers now and return: they start at the first items otherwise, and
        their start (a process each, importing the functions' module) then holds up the
        first map, when it could have gone on beside the work that prepares it."""
        if self._submit is not None:
            for _ in range(self.capacity):
                self._submit(_nothing, None)


@contextlib.contextmanager
def started(workers: Workers, preload: str) -> Iterator[Pool]:
    """A `Pool` of `workers`, stopped when the block ends (none for ``Workers(jobs=1)``:
    the work stays in this process). Local processes start as copies of one that has
    imported the module `preload` (the functions' module), rather than each importing it."""
    if workers.scheduler is None and workers.jobs == 1:
        yield Pool(None, 1)
        return
    pool = _dask_pool if workers.scheduler is not None else _local_pool
    with pool(workers, preload) as (submit, capacity):
        yield Pool(submit, capacity)



@contextlib.contextmanager
def _local_pool(workers: Workers, preload: str) -> Iterator[tuple[Submit, int]]:
    """Helper: local worker processes, started by forkserver where there is one, else spawn
    (never fork, which copies the threads' locks of a running program)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    if "forkserver" in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context("forkserver")
        # The server imports the function's module once (numpy, scipy: about a second) and
        # each worker starts as a copy of it, rather than importing them all again.
        context.set_forkserver_preload([preload])
    else:
        context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(workers.jobs, mp_context=context,
                               initializer=_worker_started)
    try:
        yield pool.submit, workers.jobs
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        # Running items would otherwise finish before the program can exit (Python 3.14
        # has pool.terminate_workers() for this).
        for process in list((getattr(pool, "_processes", None) or {}).values()):
            process.terminate()
        raise
    pool.shutdown()


def _nothing(_: Any) -> None:
    """Helper: an item that only starts its worker (`Pool.warm`)."""


def _worker_started() -> None:
    """Helper run in each worker process. Ctrl-C reaches the whole process group on a
    terminal; the parent stops the workers, which would otherwise each print a traceback.
    The processes share the cores: BLAS threads in each would only wait on each other."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # numpy's and scipy's BLAS loaded first: a limit reaches only the libraries loaded
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401

    one_blas_thread()   # for the process's life (the limit lasts until undone)


@contextlib.contextmanager
def _dask_pool(workers: Workers, preload: str) -> Iterator[tuple[Submit, int]]:
    """Helper: a client of the Dask scheduler at `workers.scheduler`."""
    try:
        import distributed
    except ImportError as exc:
        raise HamidError(f"--scheduler needs Dask's distributed scheduler: {DASK_EXTRA}") \
            from exc
    address = workers.scheduler
    try:
        client = distributed.Client(address, timeout=_CONNECT_TIMEOUT,
                                    set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise HamidError(f"--scheduler {address}: cannot connect to a Dask scheduler "
                         f"({exc})") from exc
    with client:
        capacity = max(1, sum(client.nthreads().values()))

        def submit(function: Callable[[Any], Any], item: Any) -> Any:
            # pure=False: two equal items (the same file given twice) are two tasks
            return client.submit(function, item, pure=False)

        yield submit, capacity
