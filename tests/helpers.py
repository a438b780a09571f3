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
