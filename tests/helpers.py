"""Helpers shared by test modules (pytest puts this folder on the import path)."""

from __future__ import annotations

import time
from pathlib import Path


def wait_until_integrating(process, timeout: float = 30.0) -> None:
    """Wait until the process has loaded scipy's integrators, i.e. is past its imports."""
    maps = Path(f"/proc/{process.pid}/maps")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and process.poll() is None:
        try:
            loaded = "scipy/integrate" in maps.read_text()
        except OSError:  # no /proc here: give the imports time
            time.sleep(3.0)
            return
        if loaded:
            time.sleep(0.5)
            return
        time.sleep(0.05)


def hamid_command() -> list[str]:
    """The command that runs hamid's CLI in a subprocess: this interpreter and the working
    tree (first on the children's PYTHONPATH, tests/conftest.py), never a `hamid` script
    found on PATH, which may belong to another copy."""
    import sys

    return [sys.executable, "-c", "from hamid.cli import main; main()"]


def duffing_system(*, k: str = "1.0", k3: str = "0.5", x: str = "1.0", v: str = "0.0",
                   t_end: str = "2.0", dt: str = "0.1") -> str:
    """A one-trajectory Duffing system file, each value written as given."""
    return (f'[model]\nbuiltin = "duffing"\n\n[parameters]\nk = {k}\nk3 = {k3}\n\n'
            f'[[initial]]\nx = {x}\nv = {v}\n\n[simulate]\nt_end = {t_end}\ndt = {dt}\n')
