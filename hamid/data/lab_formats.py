"""Reading the files of data-acquisition systems as tables (issue 18): MATLAB .mat (v5 through
scipy.io, v7.3 through h5py), HDF5, LabVIEW TDMS (npTDMS) and Universal File Format 58
(pyuff).

Each reader gives what `hamid.data.readers.read_columns` gives for a CSV file: numpy arrays by
column name, in file order, and the hamid metadata (a JSON object stored as the text ``hamid``: a
MATLAB variable, an HDF5 attribute, a TDMS file or group property) or None. `hamid.data.readers`
dispatches here by the file's extension. The rules that make a table of each format:

- **MATLAB**: every numeric vector variable is a column named by the variable; a struct's
  vector fields are columns named by the field; a 2-D array (rows are samples) gives one
  column per array column, named by a text array of as many names stored as
  ``<array>_columns`` (or its ``columns`` attribute for HDF5), else ``<array>_1``,
  ``<array>_2``, .... ``run.mat:name`` reads only the variable ``name``. Scalars and text
  are not columns.
- **HDF5**: ``run.h5:/group`` reads the group's 1-D datasets as columns (a 2-D dataset
  expanded as above); ``run.h5:/group/dataset`` reads one dataset: a compound dataset's
  fields, or a 2-D array's columns. Without a path, the root group is read, or its only
  dataset.
- **TDMS**: the channels of a group are the columns; ``run.tdms:group`` chooses the group
  when there are several. Waveform channels (``wf_increment``) without a time channel get
  one, ``t``, from their timing.
- **UFF 58**: each function record is a column named by its description (``id1``), and its
  abscissa is the time column ``t``. Records whose names come again start a new trajectory
  (a ``trajectory`` column, 1, 2, ...), each sharing one abscissa.

Every column must have as many values as the others; any problem is a `DataError` naming
the file. A library that is not installed is a one-line error naming
``pip install 'hamid[lab]'``.
"""

from __future__ import annotations

import importlib
import os
import re
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

from hamid.data import text_layout
from hamid.errors import DataError

__all__ = ["FORMATS", "chunks", "format_of", "read", "split"]

# Extension -> format.
FORMATS = {".mat": "mat", ".h5": "hdf5", ".hdf5": "hdf5", ".hdf": "hdf5", ".he5": "hdf5",
           ".tdms": "tdms", ".uff": "uff", ".unv": "uff"}
_KINDS = {"mat": "MATLAB", "hdf5": "HDF5", "tdms": "TDMS", "uff": "UFF"}
_PACKAGES = {"h5py": "h5py", "nptdms": "npTDMS", "pyuff": "pyuff", "scipy.io": "scipy"}
_INNER = re.compile(r"(?i)(.*?(?:" + "|".join(re.escape(s) for s in FORMATS) + r")):(.+)")
METADATA_NAME = "hamid"
_MATLAB_73 = b"MATLAB 7.3"

Columns = dict[str, Any]


def split(source: str | os.PathLike[str]) -> tuple[str, str | None]:
    """A source as its file and the path inside it: ``run.h5:/group/x`` is
    (``run.h5``, ``/group/x``); a file that exists under the whole name is that file."""
    text = os.fsdecode(source)
    match = _INNER.fullmatch(text)
    if match is None or os.path.exists(text):
        return text, None
    return match.group(1), match.group(2)


def format_of(source: str | os.PathLike[str]) -> str | None:
    """The lab format ("mat", "hdf5", "tdms", "uff") of a source by its extension, or None."""
    path, _ = split(source)
    return FORMATS.get(os.path.splitext(path)[1].lower())


def read(source: str | os.PathLike[str]) -> tuple[Columns, dict[str, Any] | None]:
    """The columns of a lab file (by name, in file order) and its hamid metadata."""
    path, inner = split(source)
    name = os.fsdecode(source)
    fmt = format_of(source)
    if fmt is None:
        raise DataError(f"{name}: not a MATLAB, HDF5, TDMS or UFF file name")
    if not os.path.isfile(path):
        reason = "is a folder, not a file" if os.path.isdir(path) else "no such file"
        raise DataError(f"{path}: {reason}")
    readers = {"mat": _read_mat, "hdf5": _read_hdf5, "tdms": _read_tdms, "uff": _read_uff}
    try:
        columns, metadata = readers[fmt](path, inner, name)
    except DataError:
        raise
    except MemoryError:
        raise
    except Exception as exc:   # the libraries' own errors for a damaged file  # noqa: BLE001
        raise DataError(f"{name}: is not a readable {_KINDS[fmt]} file "
                        f"({_first_line(exc)})") from exc
    return _checked(columns, name), metadata


def chunks(columns: Columns, names: list[str], rows: int) -> Iterator[Columns]:
    """The named columns of a table read whole, `rows` rows at a time (views, not copies)."""
    size = len(next(iter(columns.values())))
    for start in range(0, size, rows):
        yield {name: columns[name][start:start + rows] for name in names}


def _require(module: str, name: str, kind: str) -> Any:
    """Helper importing the library that reads a format, or a one-line error to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        package = _PACKAGES[module]
        raise DataError(f"{name}: reading {kind} files needs the {package} package: "
                        "pip install 'hamid[lab]'") from exc


def _checked(columns: Columns, name: str) -> Columns:
    """Helper checking that there are columns and that they have one length."""
    import numpy as np

    if not columns:
        raise DataError(f"{name}: has no numeric columns")
    lengths = {column: len(values) for column, values in columns.items()}
    if len(set(lengths.values())) > 1:
        listed = ", ".join(f"{column!r} {n}" for column, n in lengths.items())
        raise DataError(f"{name}: the columns have different lengths ({listed})")
    if not next(iter(lengths.values())):
        raise DataError(f"{name}: has columns but no data rows")
    return {column: np.ascontiguousarray(values) for column, values in columns.items()}


def _add(columns: Columns, column: str, values: Any, name: str) -> None:
    """Helper adding a column, refusing a name already taken."""
    if column in columns:
        raise DataError(f"{name}: duplicated column name {column!r}")
    columns[column] = values


def _metadata(text: Any, name: str) -> dict[str, Any] | None:
    """Helper decoding the hamid metadata stored as text (None when there is none)."""
    if text is None:
        return None
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    return text_layout.parse_metadata(str(text).encode("utf-8", errors="replace"), name)


def _is_numeric(values: Any) -> bool:
    import numpy as np

    return isinstance(values, np.ndarray) and values.dtype.kind in "biuf" and values.size > 0


def _names(values: Any) -> list[str] | None:
    """Helper reading a list of column names stored as text (a cell or char array, strings,
    or HDF5 bytes), or None when `values` is not text."""
    import numpy as np

    if isinstance(values, str | bytes):
        values = [values]
    array = np.asarray(values, dtype=object).ravel()
    names = []
    for item in array:
        item = item.decode("utf-8", errors="replace") if isinstance(item, bytes) else item
        if isinstance(item, np.ndarray) and item.dtype.kind == "U":
            item = "".join(item.ravel())
        if not isinstance(item, str):
            return None
        names.append(item.strip())
    return names


def _expand(columns: Columns, label: str, values: Any, names: Any, name: str) -> None:
    """Helper adding a numeric array: a vector as one column, a 2-D array (rows are
    samples) as one column per array column, named by `names` when they fit."""
    import numpy as np

    array = np.asarray(values)
    if array.ndim == 2 and 1 in array.shape:
        array = array.ravel()
    if array.ndim == 1:
        _add(columns, label, array, name)
        return
    if array.ndim != 2:
        raise DataError(f"{name}: {label!r} has {array.ndim} dimensions; a column is a "
                        "vector and a table a 2-D array")
    listed = _names(names) if names is not None else None
    if listed is not None and len(listed) != array.shape[1]:
        raise DataError(f"{name}: {label!r} has {array.shape[1]} columns but "
                        f"{len(listed)} column names")
    for j in range(array.shape[1]):
        _add(columns, listed[j] if listed else f"{label}_{j + 1}", array[:, j], name)


# ---------------------------------------------------------------------------------------------
# MATLAB


def _read_mat(path: str, inner: str | None, name: str) -> tuple[Columns, dict | None]:
    with open(path, "rb") as stream:
        head = stream.read(128)
    if head.startswith(_MATLAB_73):
        return _read_hdf5(path, inner, name, matlab=True)
    sio = _require("scipy.io", name, "MATLAB")
    data = sio.loadmat(path, squeeze_me=True, struct_as_record=False, chars_as_strings=True)
    variables = {key: value for key, value in data.items() if not key.startswith("__")}
    metadata = _metadata(variables.pop(METADATA_NAME, None), name)
    if inner is not None and inner not in variables:
        raise DataError(f"{name}: no variable {inner!r} (the file has "
                        f"{', '.join(map(repr, variables)) or 'none'})")
    chosen = variables if inner is None else {inner: variables[inner]}
    columns: Columns = {}
    for label, value in chosen.items():
        if isinstance(value, sio.matlab.mat_struct):
            fields = {field: getattr(value, field) for field in value._fieldnames}
            for field, item in fields.items():
                _mat_value(columns, field, item, fields, name)
        else:
            _mat_value(columns, label, value, variables, name)
    return columns, metadata


def _mat_value(columns: Columns, label: str, value: Any, scope: Mapping[str, Any],
               name: str) -> None:
    """Helper adding a MATLAB variable or struct field when it is numeric and not a scalar."""
    import numpy as np

    if _is_numeric(value) and np.ndim(value) >= 1:
        _expand(columns, label, value, scope.get(f"{label}_columns"), name)


# ---------------------------------------------------------------------------------------------
# HDF5 (and MATLAB v7.3, which is HDF5 with column-major arrays)


def _read_hdf5(path: str, inner: str | None, name: str,
               matlab: bool = False) -> tuple[Columns, dict | None]:
    h5py = _require("h5py", name, "MATLAB v7.3" if matlab else "HDF5")
    with h5py.File(path, "r") as file:
        metadata = _metadata(_h5_text(file.get(METADATA_NAME), file.attrs.get(METADATA_NAME),
                                      matlab), name)
        target = file
        if inner is not None:
            key = inner if inner.startswith("/") or not matlab else "/" + inner
            if key not in file:
                raise DataError(f"{name}: no dataset or group {inner!r} in {path}")
            target = file[key]
            if METADATA_NAME in target.attrs:
                metadata = _metadata(target.attrs[METADATA_NAME], name)
        columns: Columns = {}
        if isinstance(target, h5py.Dataset):
            _h5_dataset(columns, target, name, matlab, whole=True)
            return columns, metadata
        datasets = {key: item for key, item in target.items()
                    if isinstance(item, h5py.Dataset) and key != METADATA_NAME
                    and not key.endswith("_columns")}
        vectors = {key: item for key, item in datasets.items()
                   if _h5_length(item, matlab) is not None}
        if not vectors and len(datasets) == 1 and not matlab:   # a file holding one table
            _h5_dataset(columns, next(iter(datasets.values())), name, matlab, whole=True)
            return columns, metadata
        for key, item in datasets.items():
            _h5_dataset(columns, item, name, matlab, whole=False, names=target.get(
                f"{key}_columns"))
        if matlab:   # a struct is a group
            for key, item in target.items():
                if isinstance(item, h5py.Group) and not key.startswith("#"):
                    for field, sub in item.items():
                        if isinstance(sub, h5py.Dataset):
                            _h5_dataset(columns, sub, name, matlab, whole=False, label=field)
        if not columns:
            listed = ", ".join(repr(key) for key in target) or "nothing"
            raise DataError(f"{name}: no 1-D numeric datasets in {target.name!r} (it holds "
                            f"{listed}); give {path}:/path/to/dataset")
        return columns, metadata


def _h5_length(item: Any, matlab: bool) -> int | None:
    """Helper giving a numeric vector dataset's length, or None for anything else."""
    if item.dtype.kind not in "biuf" or (matlab and item.attrs.get("MATLAB_class") in
                                         (b"char", "char")):
        return None
    shape = item.shape
    if len(shape) == 1:
        return shape[0]
    if len(shape) == 2 and 1 in shape and max(shape) > 1:
        return max(shape)
    return None


def _h5_dataset(columns: Columns, item: Any, name: str, matlab: bool, *, whole: bool,
                label: str | None = None, names: Any = None) -> None:
    """Helper adding an HDF5 dataset's columns: the fields of a compound dataset, a vector,
    or a 2-D array's columns (when read whole, or named by its ``columns``)."""
    label = label or item.name.rsplit("/", 1)[-1]
    if item.dtype.names:   # compound: one column per field
        data = item[()]
        for field in item.dtype.names:
            _add(columns, field, data[field].ravel(), name)
        return
    if item.dtype.kind not in "biuf" or (matlab and item.attrs.get("MATLAB_class") in
                                         (b"char", "char")):
        if whole:
            raise DataError(f"{name}: {item.name!r} is not numeric")
        return
    data = item[()]
    if getattr(data, "size", 1) <= 1:   # a scalar (MATLAB's are 1 x 1)
        if whole:
            raise DataError(f"{name}: {item.name!r} is a single number, not a table")
        return
    if matlab and data.ndim == 2:
        data = data.T   # MATLAB stores arrays column-major
    names = item.attrs.get("columns") if names is None else _h5_text(names, None, matlab)
    _expand(columns, label, data, names, name)


def _h5_text(item: Any, attribute: Any, matlab: bool) -> Any:
    """Helper reading text stored as a dataset (MATLAB v7.3 char: UTF-16 codes, column-major)
    or an attribute; None when there is none."""
    if attribute is not None:
        return attribute
    if item is None or not hasattr(item, "dtype"):
        return None
    data = item[()]
    if matlab and item.dtype.kind in "iu":
        import numpy as np

        codes = np.asarray(data)
        rows = codes.T if codes.ndim == 2 else codes.reshape(1, -1)
        return [bytes(row.astype("<u2")).decode("utf-16-le") for row in rows] \
            if rows.shape[0] > 1 else bytes(rows[0].astype("<u2")).decode("utf-16-le")
    return data


# ---------------------------------------------------------------------------------------------
# LabVIEW TDMS


def _read_tdms(path: str, inner: str | None, name: str) -> tuple[Columns, dict | None]:
    nptdms = _require("nptdms", name, "TDMS")
    tdms = nptdms.TdmsFile.read(path)
    groups = [group for group in tdms.groups() if group.channels()]
    if inner is not None:
        chosen = [group for group in tdms.groups() if group.name == inner]
        if not chosen:
            raise DataError(f"{name}: no group {inner!r} (the file has "
                            f"{_listed(group.name for group in tdms.groups())})")
        group = chosen[0]
    elif len(groups) == 1:
        group = groups[0]
    elif not groups:
        raise DataError(f"{name}: has no channels")
    else:
        raise DataError(f"{name}: has {len(groups)} groups with channels "
                        f"({_listed(group.name for group in groups)}); give "
                        f"{path}:GROUP")
    metadata = _metadata(group.properties.get(METADATA_NAME,
                                              tdms.properties.get(METADATA_NAME)), name)
    columns: Columns = {}
    timed = []
    for channel in group.channels():
        data = channel[:]
        if not _is_numeric(data):
            continue
        _add(columns, channel.name, data, name)
        if "wf_increment" in channel.properties:
            timed.append(channel)
    names = {column.lower() for column in columns}
    if timed and not names & {"t", "time"} and len(timed) == len(columns):
        columns = {"t": timed[0].time_track(), **columns}
    return columns, metadata


# ---------------------------------------------------------------------------------------------
# Universal File Format 58


def _read_uff(path: str, inner: str | None, name: str) -> tuple[Columns, dict | None]:
    pyuff = _require("pyuff", name, "UFF")
    import numpy as np

    sets = pyuff.UFF(path).read_sets()
    sets = [sets] if isinstance(sets, dict) else sets   # pyuff gives one set as a dict
    records = [record for record in sets if record.get("type") == 58]
    if not records:
        raise DataError(f"{name}: has no function records (UFF dataset 58)")
    trajectories: list[dict[str, Any]] = []
    abscissas: list[Any] = []
    for number, record in enumerate(records, 1):
        label = str(record.get("id1") or "").strip() or \
            f"{record.get('rsp_node', number)}:{record.get('rsp_dir', 0)}"
        if inner is not None and label != inner and label not in inner.split(","):
            continue
        data = np.asarray(record["data"])
        if np.iscomplexobj(data):
            raise DataError(f"{name}: record {number} ({label!r}) is complex; a column is "
                            "a real time series")
        k = sum(label in trajectory for trajectory in trajectories)
        if k == len(trajectories):
            trajectories.append({})
            abscissas.append(np.asarray(record["x"], dtype=float))
        if not np.array_equal(np.asarray(record["x"], dtype=float), abscissas[k]):
            raise DataError(f"{name}: record {number} ({label!r}) has another abscissa "
                            "than the records before it")
        trajectories[k][label] = data.astype(float)
    labels = list(trajectories[0])
    for k, trajectory in enumerate(trajectories[1:], 2):
        if list(trajectory) != labels:
            raise DataError(f"{name}: trajectory {k} has the records "
                            f"{_listed(trajectory)} where the first has {_listed(labels)}")
    columns: Columns = {}
    if len(trajectories) > 1:
        columns["trajectory"] = np.concatenate([np.full(len(x), k, dtype=np.int64)
                                                for k, x in enumerate(abscissas, 1)])
    if "t" in labels:
        raise DataError(f"{name}: a record is named 't', the name of the abscissa")
    columns["t"] = np.concatenate(abscissas)
    for label in labels:
        columns[label] = np.concatenate([trajectory[label] for trajectory in trajectories])
    return columns, None


def _listed(names: Iterable[str]) -> str:
    return ", ".join(repr(name) for name in names)


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__
