"""The fit's options: their specification in groups (`OPTION_GROUPS`), the choices the user
types, their checks, and option values (`FitOptions`).

No numpy, pandas or pyarrow at import: the CLI takes its choice lists from here.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from decimal import Decimal
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from hamid.errors import UsageError

if TYPE_CHECKING:
    from hamid.data.text_layout import TextOptions


def parse_mapping(text: str, *, option: str) -> dict[str, str]:
    """Parse ``NAME=COLUMN,...`` as given to an option such as ``--columns``.

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option's name, for messages.

    Returns
    -------
    mapping : dict
        Name -> value, in the order given.

    Raises
    ------
    UsageError
        An item is not ``NAME=VALUE`` or a name is given twice.

    Examples
    --------
    >>> parse_mapping("x=pos1, vx=vel1", option="--columns")
    {'x': 'pos1', 'vx': 'vel1'}
    """
    return _parse_items(text, option, "NAME=COLUMN", lambda key, value, item: value)


def parse_float_mapping(text: str, *, option: str) -> dict[str, float]:
    """Parse ``NAME=NUMBER,...`` as given to options such as ``--noise`` and ``--fix``.

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option's name, for messages.

    Returns
    -------
    mapping : dict
        Name -> finite number, in the order given.

    Raises
    ------
    UsageError
        An item is not ``NAME=NUMBER``, a number is not finite, or a name is given twice.

    Examples
    --------
    >>> parse_float_mapping("x=0.01,vx=2e-2", option="--noise")
    {'x': 0.01, 'vx': 0.02}
    """

    def to_float(key: str, value: str, item: str) -> float:
        try:
            number = float(value)
        except ValueError:
            raise UsageError(f"{option}: {item!r}: {value!r} is not a number") from None
        if not math.isfinite(number):
            raise UsageError(f"{option}: {item!r}: {value!r} is not a finite number")
        return number

    return _parse_items(text, option, "NAME=NUMBER", to_float)


def _parse_items(
    text: str, option: str, form: str, convert: Callable[[str, str, str], Any]
) -> dict[str, Any]:
    """Helper function splitting ``NAME=VALUE,...`` and checking each item."""
    result: dict[str, Any] = {}
    if not text.strip():
        raise UsageError(f"{option}: empty value; expected {form},...")
    for raw in text.split(","):
        item = raw.strip()
        key, equals, value = (part.strip() for part in item.partition("="))
        if not equals or not key or not value:
            raise UsageError(f"{option}: {item!r} is not of the form {form}")
        if key in result:
            raise UsageError(f"{option}: {key!r} is given twice")
        result[key] = convert(key, value, item)
    return result


def percent(level: float | Decimal) -> str:
    """A confidence level as a percentage, e.g. 95%, never rounded to 100%: how reports and
    warnings write the option `level`.

    Decimal arithmetic on the level's shortest repr: 100 * 0.9 is 90.00000000000001 in
    binary, and 6 digits would turn 0.9999999999999999 into "100%".
    """
    if not isinstance(level, Decimal):
        level = Decimal(repr(float(level)))
    return f"{(level * 100).normalize():f}%"


METHODS = ("auto", "joint", "weak", "energy")
COVARIANCE_KINDS = ("hac", "classical", "hc", "bootstrap")
VELOCITY_SOURCES = ("auto", "measured", "savgol")
TIME_UNITS = ("s", "ms", "us", "ns")   # naming.TIME_UNITS, without importing it
GAP_POLICIES = ("split", "error")
# hamid.model.dissipation.SHORTHAND, without importing numpy at the CLI's start
DAMPING_KINDS = ("viscous", "coulomb", "quadratic")
SELECTION_CRITERIA = ("bic", "aic", "cv")   # of `hamid select` (hamid.selection.best_subsets)
SAVGOL_ORDER = 5

# Bootstrap replicates (fit's --bootstrap, select's --stability) each refit every row:
# at most this many, and at most this many rows refitted in all (a few minutes), checked
# before the first; --bootstrap 1000000000 ran until killed.
MAX_REPLICATES = 100_000
REPLICATE_ROWS = 1_000_000_000


def check_replicates(option: str, replicates: int, rows: int | None = None) -> None:
    """Refuse more bootstrap replicates than `MAX_REPLICATES`, or, given the rows each
    refits, more rows refitted in all than `REPLICATE_ROWS`."""
    if replicates > MAX_REPLICATES:
        raise UsageError(f"{option} {replicates:,}: more replicates than the "
                         f"{MAX_REPLICATES:,} allowed")
    if rows is not None and replicates * rows > REPLICATE_ROWS:
        raise UsageError(f"{option} {replicates:,} replicates of {rows:,} rows would refit "
                         f"{replicates * rows:,} rows, more than {REPLICATE_ROWS:,}; use at "
                         f"most {REPLICATE_ROWS // rows:,} replicates")


# Files that take more than this once decoded (8 bytes a cell, `hamid.data.input_size`) are read in
# chunks when the options allow it: the chunked fit is the fit in memory, faster and in a
# third of the memory.
STREAM_BYTES = 64 << 20
CHUNK_ROWS = 1 << 18
# The trajectory refinement of a chunked fit holds the records (times, states, trajectory
# numbers) in memory, 8 bytes a value; larger records are left unrefined.
REFINEMENT_BYTES = 1 << 30


# The option specification: every keyword of `hamid.fit` in one group, each group what one
# part of the fit is asked. FitOptions' fields are these names but `progress` (a callback,
# not part of what the fit answers); the command line declares each group's options once
# (`hamid.cli.option_groups`), by these names, and tests/test_option_spec.py checks
# FitOptions, fit's keywords and the commands' options against this table.
OPTION_GROUPS: Mapping[str, tuple[str, ...]] = MappingProxyType({
    # How a data file is read: every command that reads data takes these, and a report
    # records those given (`data.reading`) for `plot` to read the data again.
    "reading": ("columns", "time", "time_unit", "trajectory", "scale", "gaps", "format",
                "delimiter", "decimal", "skip_rows", "units_row"),
    # Where the velocities come from: the file, or the positions differentiated by a
    # Savitzky-Golay filter of this window and order.
    "velocities": ("velocity", "window", "order"),
    # How the parameters are estimated: which rows (method, weak_window), which forces
    # besides the energy's (damping), which parameters are known (fix), and the measurement
    # noise: rows weighted by the variance it puts into them (noise), its bias removed
    # (bias_correct). The noise is here, not with the velocities, because it weighs the
    # rows of every column, positions too.
    "method": ("method", "weak_window", "damping", "fix", "noise", "bias_correct"),
    # How the estimates' uncertainty is computed: the estimator, the bounds' level, the
    # bootstrap's replicates and seed.
    "covariance": ("cov", "level", "bootstrap", "seed"),
    # How the fit runs, in processes, chunks or memory, and what it says while it runs:
    # the estimates stay the same (but chunks leave out `auto`'s refinement).
    "run": ("jobs", "chunk_rows", "in_memory", "progress"),
})
READING_OPTIONS = OPTION_GROUPS["reading"]
FIT_KEYWORDS = tuple(name for names in OPTION_GROUPS.values() for name in names)


@dataclass(frozen=True)
class FitOptions:
    """Everything `hamid.fit` is asked to do besides the data and the model, checked once.

    The fields are `hamid.fit`'s keyword arguments (see there) but `progress`, in the
    groups of `OPTION_GROUPS`; `damping` is parsed into its kinds and `fix` into floats.
    Building one raises a UsageError for any value or combination that makes no sense,
    before any data are read.
    """

    # reading
    columns: Mapping[str, str] | None = None
    time: str | None = None
    time_unit: str | None = None
    trajectory: str | None = None
    scale: Mapping[str, float] | None = None
    gaps: str = "split"
    format: str | None = None
    delimiter: str | None = None
    decimal: str | None = None
    skip_rows: int = 0
    units_row: bool | None = None
    # velocities
    velocity: str = "auto"
    window: int | None = None
    order: int = SAVGOL_ORDER
    # method
    method: str = "auto"
    weak_window: float | None = None
    damping: tuple[str, ...] = ()
    fix: Mapping[str, float] = field(default_factory=dict)
    noise: str | Mapping[str, float] | None = None
    bias_correct: bool = False
    # covariance
    cov: str = "hac"
    level: float = 0.95
    bootstrap: int = 200
    seed: int | None = None
    # run
    jobs: int | None = None
    chunk_rows: int | None = None
    in_memory: bool = False

    def __post_init__(self) -> None:
        _ = self.text   # building it checks the text-layout options
        if self.time_unit is not None:
            _check_choice(self.time_unit, TIME_UNITS, "time_unit")
        _check_choice(self.gaps, GAP_POLICIES, "gaps")
        for column, factor in (self.scale or {}).items():
            if not isinstance(factor, int | float) or not 0 < abs(factor) < float("inf"):
                raise UsageError(f"--scale: {column}={factor!r} is not a finite non-zero "
                                 "number")
        _check_choice(self.method, METHODS, "method")
        _check_choice(self.cov, COVARIANCE_KINDS, "cov")
        if not 0 < self.level < 1:
            raise UsageError(f"level must be between 0 and 1, found {self.level!r}")
        if self.bias_correct and not self.weighted:
            raise UsageError("--bias-correct needs --noise (auto or COL=SIGMA,...)")
        if self.bias_correct and self.cov == "bootstrap":
            raise UsageError("--bias-correct cannot be combined with --cov bootstrap (the "
                             "refits would not be corrected); use --cov hac")
        if self.cov == "bootstrap" and self.bootstrap < 10:
            raise UsageError(f"bootstrap needs at least 10 replicates, found {self.bootstrap}")
        check_replicates("--bootstrap", self.bootstrap)
        if self.weak_window is not None and not 0 < self.weak_window < float("inf"):
            raise UsageError(f"--weak-window must be a positive number of seconds, "
                             f"found {self.weak_window!r}")
        if self.velocity != "savgol" and (self.window is not None
                                          or self.order != SAVGOL_ORDER):
            raise UsageError("--window and --order apply only to --velocity savgol")
        _check_choice(self.velocity, VELOCITY_SOURCES, "velocity")
        object.__setattr__(self, "damping", parse_damping(self.damping))
        object.__setattr__(self, "fix", dict(self.fix or {}))
        if self.chunk_rows is not None and self.chunk_rows < 1:
            raise UsageError("--chunk-rows: must be a positive number of rows")
        if self.jobs is not None and (isinstance(self.jobs, bool) or not isinstance(self.jobs, int)
                                      or self.jobs < 1):
            raise UsageError(f"--jobs must be a whole number of at least 1, found {self.jobs!r}")

    @property
    def text(self) -> TextOptions:
        """How delimited text is read (None fields: detected)."""
        from hamid.data.text_layout import TextOptions

        return TextOptions(self.delimiter, self.decimal, self.skip_rows, self.units_row)

    @property
    def reading(self) -> dict[str, Any]:
        """The reading options given (`READING_OPTIONS` not at their defaults), as plain
        data: what the report records in `data.reading`."""
        defaults = {f.name: f.default for f in fields(self)}
        return {name: dict(value) if isinstance(value, Mapping) else value
                for name in READING_OPTIONS
                if (value := getattr(self, name)) != defaults[name]}

    @property
    def weighted(self) -> bool:
        """Whether rows are weighted by the measurement noise (--noise)."""
        return self.noise not in (None, "none")

    @property
    def linear_asked(self) -> str | None:
        """Why these options ask for the linear fit's own estimate where an automatic fit
        would be refined by trajectories (its covariance, its bias correction), or None."""
        if self.cov != "hac":
            return (f"the trajectory fit has a covariance of its own, and --cov {self.cov} "
                    "asks for that of the linear fit")
        if self.bias_correct:
            return "--bias-correct asks for the linear fit"
        return None

    def chunking(self, data: Any, model_obstacle: str = "") -> int | None:
        """The rows per chunk when `data` is read in chunks, or None to read it whole.

        A file that takes over `STREAM_BYTES` once decoded (`hamid.data.input_size.decoded_bytes`,
        whatever its size on disk) is read in chunks when the options allow it;
        `chunk_rows` asks for chunks, which is an error when they are not possible. A model
        may need the data in memory, `model_obstacle` saying why (`loading.in_memory_only`).
        """
        obstacle = self._needs_memory(data) or model_obstacle
        if self.chunk_rows is not None and (obstacle or self.in_memory):
            raise UsageError(f"--chunk-rows: "
                             f"{obstacle or 'in_memory asks for the data in memory'}")
        if self.chunk_rows is not None:
            return self.chunk_rows
        if obstacle or self.in_memory:
            return None
        from hamid.data.input_size import decoded_bytes

        if decoded_bytes(data, format=self.format, text=self.text) > STREAM_BYTES:
            return CHUNK_ROWS
        return None

    def _needs_memory(self, data: Any) -> str:
        """Why the fit needs all the data in memory, or "" when it can read them in chunks."""
        if not isinstance(data, str | os.PathLike) or os.fspath(data) == "-" \
                or not os.path.isfile(data):
            return "chunks need one file (not a list, a DataFrame or a device)"
        if self.velocity == "savgol":
            return "derived velocities (--velocity savgol) need the data in memory"
        if self.weighted:
            return "noise weighting (--noise) needs the data in memory"
        if self.damping:
            return "damping (--damping) needs the data in memory"
        if self.cov == "bootstrap":
            return "--cov bootstrap needs the data in memory"
        return ""


def _check_choice(value: str, choices: tuple[str, ...], option: str) -> None:
    if value not in choices:
        raise UsageError(f"{option} must be one of {', '.join(choices)}, found {value!r}")


def parse_damping(damping: str | Sequence[str] | None) -> tuple[str, ...]:
    """Damping kinds from "none", "viscous,coulomb" or a list; unknown kinds are errors.

    None or an empty list is no damping (FitOptions' default, and what it parses "none"
    into); an empty text is a mistake on the command line."""
    if damping is None:
        return ()
    items = damping.split(",") if isinstance(damping, str) else list(damping)
    kinds = [item.strip() for item in items if item.strip()]
    if not kinds and not isinstance(damping, str) and not items:
        return ()
    if not kinds:
        raise UsageError("--damping: empty value; expected none or any of "
                         f"{', '.join(DAMPING_KINDS)} (comma separated)")
    if kinds == ["none"]:
        return ()
    for kind in kinds:
        if kind not in DAMPING_KINDS:
            raise UsageError(f"--damping: unknown kind {kind!r} (choose none or any of "
                             f"{', '.join(DAMPING_KINDS)}, comma separated)")
    if len(set(kinds)) != len(kinds):
        raise UsageError(f"--damping: a kind is given twice in {','.join(kinds)!r}")
    return tuple(kinds)
