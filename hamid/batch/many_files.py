"""Many recordings: one independent fit per file (`hamid fit --each`, `hamid.fit_each`).

The sources (files, folders, glob patterns, URLs) are expanded into files; each is fitted
by `hamid.fit` with the same options, in this process, in local worker processes or on a
Dask cluster (`hamid.executor`), and the outcomes come back in the order of the files: a
`FitResult`, or the `HamidError` that stopped that file's fit while the others went on.

A file is read where its fit runs: a path the workers share, or a URL that pyarrow opens
(``s3://``, ``gs://``, ``hdfs://``, ``file://``). With `ship_data` the bytes are read here
and sent. Either way the report names the source as given.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import os
import re
import tempfile
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hamid.api import fit
from hamid.data import lab_formats, readers
from hamid.errors import DataError, HamidError, UsageError
from hamid.executor import Workers, ordered_map
from hamid.report import comparison
from hamid.result.fit_result import FitResult

if TYPE_CHECKING:
    import pandas as pd

    from hamid.model.models import Model

__all__ = ["Fits", "expand_sources", "fit_each", "iter_fits"]

_URL = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://")
_GLOB = re.compile(r"[*?[]")

Outcome = FitResult | HamidError


def expand_sources(patterns: Sequence[str | os.PathLike[str]]) -> list[str]:
    """The files to fit one by one: each file as given, a folder's data files (CSV, TSV,
    Parquet, compressed text, lab formats; not its hidden files nor its subfolders) and a
    glob pattern's files (``**`` spans folders, but not linked ones), each in natural
    order (run2 before run10); URLs as given. A file named twice (or through a link) is
    fitted once, where it first comes.

    Raises
    ------
    DataError
        A name that is neither a file, a folder, a URL nor a pattern with matches, or a
        folder without data files.
    UsageError
        Standard input (``-``), which cannot be one of many files.
    """
    files: list[str] = []
    for pattern in map(os.fsdecode, patterns):
        if readers.is_stdio(pattern):
            raise UsageError("--each fits files one by one; standard input ('-') cannot be "
                             "one of them")
        if _URL.match(pattern) or os.path.isfile(lab_formats.split(pattern)[0]):
            files.append(pattern)
        elif os.path.isdir(pattern):
            found = sorted((entry.path for entry in os.scandir(pattern)
                            if entry.is_file() and not entry.name.startswith(".")
                            and _is_data_file(entry.path)), key=_natural)
            if not found:
                raise DataError(f"{pattern}: the folder holds no data files (.csv, .tsv, "
                                ".parquet, compressed or lab files)")
            files.extend(found)
        elif _GLOB.search(pattern):
            found = sorted(_glob(pattern), key=_natural)
            if not found:
                raise DataError(f"{pattern}: no file matches the pattern")
            files.extend(found)
        else:
            raise DataError(f"{pattern}: no such file or folder")
    once: dict[object, str] = {}
    for file in files:
        once.setdefault(_identity(file), file)
    return list(once.values())


def _glob(pattern: str) -> Iterator[str]:
    """Helper: the files a pattern matches, as glob.glob(pattern, recursive=True) finds
    them (wildcards skip hidden names), without entering linked folders: a link loop
    (``a/b/up -> ..``) would give each file under it forty times."""
    parts = pattern.split(os.sep)
    start = next(k for k, part in enumerate(parts) if _GLOB.search(part))
    top = os.sep.join(parts[:start]) or (os.sep if pattern.startswith(os.sep) else "")
    wanted = parts[start:]   # a last part "" (``runs/*/``) asks for folders: no file
    for folder, subfolders, names in os.walk(top or os.curdir):
        relative = os.path.relpath(folder, top or os.curdir)
        inner = [] if relative == os.curdir else relative.split(os.sep)
        if "**" not in wanted and len(inner) >= len(wanted) - 1:
            subfolders.clear()   # deep enough for the pattern
        for name in names:
            path = os.path.join(top, *inner, name)
            if _matches([*inner, name], wanted) and os.path.isfile(path):
                yield path


def _matches(parts: Sequence[str], pattern: Sequence[str]) -> bool:
    """Helper: whether path parts match pattern parts as glob's do (``**``: any number of
    folders; a wildcard matches a hidden name only when the pattern starts with a dot)."""
    if not pattern:
        return not parts
    head, rest = pattern[0], pattern[1:]
    if head == "**":
        return any(_matches(parts[k:], rest) for k in range(len(parts) + 1)
                   if not any(part.startswith(".") for part in parts[:k]))
    return (bool(parts) and fnmatch.fnmatchcase(parts[0], head)
            and (head.startswith(".") or not parts[0].startswith("."))
            and _matches(parts[1:], rest))


def _identity(source: str) -> object:
    """Helper: what tells two sources apart: a local file by device and inode (and the
    variable of a lab file), a URL by itself."""
    if _URL.match(source):
        return source
    path, inner = lab_formats.split(source)
    status = os.stat(path)
    return status.st_dev, status.st_ino, inner


def _natural(path: str) -> list[str | int]:
    """Helper: a sort key that puts run2 before run10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path)]


def _is_data_file(path: str) -> bool:
    """Helper: whether a folder's file is one hamid reads, by its extension."""
    return readers.input_format(path) is not None or lab_formats.format_of(path) is not None


class Fits(list[Outcome]):
    """The outcomes of `fit_each`, in the order of the files: a `FitResult` per file
    fitted, the `HamidError` that stopped each other one; `sources` names the files."""

    def __init__(self, sources: Sequence[str], outcomes: Sequence[Outcome]):
        super().__init__(outcomes)
        self.sources = tuple(sources)

    def to_frame(self) -> pd.DataFrame:
        """One row per file and parameter, an error row per failed file
        (`comparison.ROW_COLUMNS`)."""
        import pandas as pd

        rows = [row for source, outcome in zip(self.sources, self, strict=True)
                for row in comparison.parameter_rows(comparison.record(source, outcome))]
        return pd.DataFrame(rows, columns=list(comparison.ROW_COLUMNS))


def fit_each(files: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
             model: str | os.PathLike[str] | Model | None = None, *,
             jobs: int | None = None, scheduler: str | None = None, ship_data: bool = False,
             **fit_options: Any) -> Fits:
    """Fit each file by itself, in parallel, with the same options.

    Parameters
    ----------
    files : path, folder, glob pattern, URL, or a list of them
        The recordings; see `expand_sources`.
    model : str, path or Model, optional
        As for `hamid.fit`; a model file is read once, here.
    jobs : int, optional
        Local worker processes (default: one per core, at most one per file; 1 fits in
        this process).
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://HOST:PORT``) whose workers fit the files
        instead; default ``$DASK_SCHEDULER_ADDRESS`` when `jobs` is not given. Needs
        ``pip install 'hamid[dask]'``.
    ship_data : bool
        Read the files here and send their bytes to the workers, which then need no access
        to them.
    **fit_options
        Any keyword of `hamid.fit` but `progress`; checked once, before any fit.

    Returns
    -------
    Fits
        A list with a `FitResult` (without per-sample residuals) or a `HamidError` per
        file, in the order of the files, and `to_frame()`.

    Examples
    --------
    >>> fits = hamid.fit_each("runs/", model="duffing", jobs=2)  # doctest: +SKIP
    >>> fits.to_frame().pivot(index="source", columns="parameter", values="estimate")
    """
    sources = expand_sources([files] if isinstance(files, str | os.PathLike) else files)
    outcomes = iter_fits(sources, model, fit_options,
                         Workers.choose(jobs, scheduler, len(sources)), ship_data=ship_data)
    return Fits(sources, list(outcomes))


def iter_fits(sources: Sequence[str], model: str | os.PathLike[str] | Model | None,
              fit_options: Mapping[str, Any], workers: Workers, *,
              ship_data: bool = False) -> Iterator[Outcome]:
    """The outcome of each source's fit, in the order of the sources, as they finish.

    The options and the model are checked here first, so that a mistake in them is one
    error rather than one per file.
    """
    import inspect

    from hamid.options import FitOptions

    if "progress" in fit_options:
        raise UsageError("fit_each: 'progress' is for one fit; fit_each's fits run elsewhere")
    try:
        arguments = inspect.signature(fit).bind(None, model, **fit_options)
    except TypeError as exc:
        raise UsageError(f"fit_each: {exc}") from None
    arguments.apply_defaults()
    FitOptions(**{name: value for name, value in arguments.arguments.items()
                  if name not in ("data", "model", "progress")})
    if isinstance(model, str | os.PathLike):
        from hamid.model.models import load_model

        model = load_model(model)   # read once; workers elsewhere need no copy of the file
    if ship_data and workers.scheduler is None:
        raise UsageError("--ship-data applies only with --scheduler (local workers read "
                         "the files themselves)")
    # the files are the parallel work: each fit's refinement stays in its own process
    tasks = (_Task(source, model, {**fit_options, "jobs": 1}, tuple(warnings.filters),
                   *(_shipped(source) if ship_data else (None, None)))
             for source in sources)
    yield from ordered_map(_fit_task, tasks, workers)


@dataclass(frozen=True, slots=True)
class _Task:
    """One file's fit as a worker receives it: the caller's warning filters (a worker
    process starts with Python's own) and, when shipped, the file's bytes or the error
    reading them."""

    source: str
    model: Model | None
    options: dict[str, Any]
    filters: tuple[Any, ...]
    data: bytes | None = None
    error: HamidError | None = None


def _shipped(source: str) -> tuple[bytes | None, HamidError | None]:
    """Helper: a file's bytes read here to send, or the error reading them."""
    try:
        return _read_bytes(lab_formats.split(source)[0]), None
    except HamidError as exc:
        return None, exc


def _read_bytes(path: str) -> bytes:
    """Helper: the bytes of a local file or of a URL that pyarrow opens."""
    if not _URL.match(path):
        return readers.read_bytes(path)[0]
    import pyarrow as pa
    import pyarrow.fs

    try:
        filesystem, inner = pyarrow.fs.FileSystem.from_uri(path)
        with filesystem.open_input_stream(inner) as stream:
            return stream.read()
    except (pa.ArrowException, OSError) as exc:
        raise DataError(f"{path}: cannot read: {readers.first_line(exc)}") from exc


def _fit_task(task: _Task) -> Outcome:
    """Helper run by a worker: one file's fit, or the error that stopped it."""
    with warnings.catch_warnings():
        warnings.filters[:] = list(task.filters)
        try:
            if task.error is not None:
                raise task.error
            path, inner = lab_formats.split(task.source)
            if task.data is None and not _URL.match(path):
                result = fit(task.source, task.model, **task.options)
            else:
                with tempfile.TemporaryDirectory(prefix="hamid-") as folder:
                    local = os.path.join(folder, os.path.basename(path.rstrip("/")) or "data")
                    with open(local, "wb") as stream:
                        stream.write(task.data if task.data is not None else _read_bytes(path))
                    local_source = local if inner is None else f"{local}:{inner}"
                    try:
                        result = _renamed(fit(local_source, task.model, **task.options),
                                          local_source, task.source)
                    except HamidError as exc:
                        raise type(exc)(str(exc).replace(local_source, task.source)) from None
        except HamidError as exc:
            return exc
        except Exception as exc:   # one file's failure, a bug included, stops only its fit
            return _failure(task.source, exc)
    # the per-sample residuals are bulk data that no batch output shows
    return dataclasses.replace(result, samples=None)


def _failure(source: str, exc: Exception) -> HamidError:
    """Helper: an error that is not hamid's own, as one line naming the file."""
    if isinstance(exc, MemoryError):
        return HamidError(f"{source}: out of memory while fitting it")
    return HamidError(f"{source}: internal error ({type(exc).__name__}: "
                      f"{readers.first_line(exc)}); this is a bug in hamid")


def _renamed(result: FitResult, local: str, source: str) -> FitResult:
    """Helper: a result fitted from a local copy, naming the source instead."""
    data = {**result.data, "sources": [source]}
    provenance = result.provenance
    if provenance is not None:
        inputs = [{**item, "path": source} for item in provenance["inputs"]]
        provenance = {**provenance, "inputs": inputs}
    return dataclasses.replace(result, data=data, provenance=provenance,
                               warnings=tuple(w.replace(local, source)
                                              for w in result.warnings))
