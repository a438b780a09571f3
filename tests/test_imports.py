"""Start-up cost: the command line and built-in fits import only what they need."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SAMPLE = Path(__file__).resolve().parent.parent / "sample_data" / "duffing.csv"
HEAVY = ("numpy", "scipy", "pandas", "pyarrow", "sympy", "rich", "matplotlib")


def _loaded_after(code: str) -> set[str]:
    probe = f"{code}\nimport sys\nprint(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True)
    return set(out.stdout.split())


@pytest.mark.parametrize("code", ["import hamid.cli.app", "import hamid"])
def test_importing_the_cli_loads_nothing_heavy(code):
    assert _loaded_after(code) == set()


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_fitting_a_builtin_model_imports_neither_sympy_nor_pandas(tmp_path, suffix):
    from hamid.data import readers, writing

    path = tmp_path / f"duffing{suffix}"
    table, metadata = readers.read_table(SAMPLE)
    writing.write_table(table, str(path), metadata=metadata)
    loaded = _loaded_after(f"import hamid\nhamid.fit({str(path)!r})")
    assert {"numpy", "pyarrow"} <= loaded  # the probe works
    assert not loaded & {"sympy", "pandas", "matplotlib"}   # figures only when asked for


def test_the_refinement_imports_neither_scipy_integrate_nor_scipy_optimize():
    """auto's trajectory refinement steps with hamid.refine.dop853: scipy.integrate (and the
    scipy.optimize it imports) would cost a small fit some 0.15 s."""
    probe = (f"import sys, hamid\nresult = hamid.fit({str(SAMPLE)!r})\n"
             "print(result.method['refinement']['applied'], "
             "'scipy.integrate' in sys.modules, 'scipy.optimize' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["True", "False", "False"]
