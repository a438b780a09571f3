"""hamid: identify nonlinear vibrating systems by fitting their energy.

The heavy parts (numpy, scipy, pandas, sympy) load on first use, so that the command line
starts fast.
"""

from __future__ import annotations

import importlib
from typing import Any

from hamid.errors import DataError, FitError, HamidError, ModelError, UsageError

__version__ = "0.1.0"

__all__ = [
    "DataError",
    "FitError",
    "HamidError",
    "ModelError",
    "UsageError",
    "__version__",
    "fit",
    "fit_each",
    "load_model",
    "select",
    "simulate",
    "simulate_realizations",
]

_LAZY = {"fit": "hamid.api", "simulate": "hamid.simulation", "load_model": "hamid.api",
         "select": "hamid.selection.select_terms", "fit_each": "hamid.batch.many_files",
         "simulate_realizations": "hamid.simulation"}


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module 'hamid' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value  # cache: later lookups skip __getattr__
    return value
